"""Parsing untrusted input: any failure becomes one :class:`InputError` naming the input and field.

Model metadata, scene files, system JSON, checkpoints and command-line numbers come from outside
the package. Catching a list of named exception types lets the unnamed ones (RecursionError from
nested JSON, OverflowError from huge numbers, TypeError from odd types, KeyError, ...) escape as
tracebacks. Every parser of such input runs inside :func:`parsing` instead, so whatever goes wrong
comes out as one ValueError with one line that says where.

>>> with parsing("scene paper.toml", "h"):
...     float("x")
Traceback (most recent call last):
...
poisson_rs.untrusted.InputError: scene paper.toml, field h: could not convert string to float: 'x'
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["InputError", "parsing"]

#: Longest message kept from the underlying exception: a hostile input can make it huge.
_MAX_DETAIL = 300


class InputError(ValueError):
    """Untrusted input that cannot be used. ``source`` names the input (a file, a flag),
    ``field`` the part of it (a key, a tensor), ``problem`` what is wrong, in one line."""

    def __init__(self, source: str, field: str | None, problem: str) -> None:
        self.source = source
        self.field = field
        self.problem = problem
        where = f"{source}, field {field}" if field else source
        super().__init__(f"{where}: {problem}")


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, RecursionError):
        text = "nested too deeply"
    elif isinstance(exc, (OverflowError, KeyError)):
        text = f"{type(exc).__name__}: {text}"
    return text if len(text) <= _MAX_DETAIL else text[: _MAX_DETAIL - 1] + "…"


@contextmanager
def parsing(source: str, field: str | None = None) -> Iterator[None]:
    """Runs the block; any exception (but an :class:`InputError` from an inner block, which is
    re-raised as it is, and MemoryError, KeyboardInterrupt and SystemExit, which are not input
    errors) becomes an :class:`InputError` for ``source`` and ``field``."""
    try:
        yield
    except InputError:
        raise
    except (MemoryError, KeyboardInterrupt, SystemExit, GeneratorExit):
        raise
    except Exception as exc:  # the point: no unnamed failure escapes
        raise InputError(source, field, _one_line(exc)) from None

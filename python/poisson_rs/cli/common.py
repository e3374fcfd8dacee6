"""What the subcommands share: checked number options, one-line errors, tables, systems by name,
the ``--scheduler`` flag and progress lines.

Every number a user types is parsed by :func:`number`: finite, inside its bounds, an integer where
one is needed, and turned into ONE line and exit status 2 when it is not (argparse's usage block
is not printed: a script reading stderr gets one line).
"""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from ..threads import max_threads

if TYPE_CHECKING:
    pass

#: Most steps any subcommand takes from one state (the step count, not the memory, is bounded
#: here; a subcommand that stores every step bounds it again by the memory it needs).
MAX_STEPS = 10**9
#: Largest step size or horizon a command accepts (time units).
MAX_TIME = 1e9


class UsageError(ValueError):
    """A command line that does not parse; ``main`` prints it as one line and returns 2."""


class Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are a :class:`UsageError` (one line, exit status 2 from
    ``main``) instead of a usage block and ``sys.exit``."""

    def error(self, message: str) -> Any:
        one = " ".join(message.split())
        raise UsageError(f"{self.prog}: {one}")


def _parse_int(text: str) -> int:
    """An integer from "10", "1_000" or an integral float spelling such as "1e4"."""
    try:
        return int(text, 10)
    except ValueError:
        value = float(text)
        if not (math.isfinite(value) and value == math.floor(value)):
            raise ValueError(f"not an integer: {text!r}") from None
        return int(value)


def number(
    *,
    integer: bool = False,
    low: float | None = None,
    high: float | None = None,
    low_open: bool = False,
) -> Callable[[str], Any]:
    """An argparse ``type`` for a checked number: finite, ``low`` ≤ x (``low`` < x with
    ``low_open``) and x ≤ ``high``; an ``int`` when ``integer``. Any failure is one
    ``ArgumentTypeError`` line that says what was expected and what was given."""
    lo = "-inf" if low is None else f"{low:g}"
    hi = "inf" if high is None else f"{high:g}"
    want = ("an integer" if integer else "a finite number") + (
        f" in {'(' if low_open else '['}{lo}, {hi}]"
    )

    def parse(text: str) -> Any:
        shown = text if len(text) <= 40 else text[:39] + "…"
        try:
            value: Any = _parse_int(text) if integer else float(text)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"needs {want}, got {shown!r}") from None
        ok = math.isfinite(value)
        if ok and low is not None:
            ok = value > low if low_open else value >= low
        if ok and high is not None:
            ok = value <= high
        if not ok:
            raise argparse.ArgumentTypeError(f"needs {want}, got {shown!r}")
        return value

    parse.__name__ = "integer" if integer else "number"
    return parse


#: The usual kinds of option.
POSITIVE = number(low=0.0, low_open=True, high=MAX_TIME)
STEPS = number(integer=True, low=1, high=MAX_STEPS)
FRACTION = number(low=0.0, high=1.0)


def threads_type(text: str) -> int:
    """``--threads``: an integer in [1, 4 × cores]."""
    return int(number(integer=True, low=1, high=max_threads())(text))


def table(rows: Sequence[dict[str, Any]], cols: Sequence[str]) -> str:
    """A plain-text table; floats as %.2e, NaN (an unknown quantity) as "n/a"."""

    def fmt(v: Any) -> str:
        if isinstance(v, float):
            return "n/a" if math.isnan(v) else f"{v:.2e}"
        return "n/a" if v is None else str(v)

    cells = [[fmt(r.get(c)) for c in cols] for r in rows]
    widths = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    line = "  ".join(c.ljust(w) for c, w in zip(cols, widths, strict=True))
    body = ["  ".join(x.ljust(w) for x, w in zip(r, widths, strict=True)) for r in cells]
    return "\n".join([line, "-" * len(line), *body])


def check_positive(**values: float) -> None:
    """ValueError naming the first option that is not a finite number > 0."""
    for name, v in values.items():
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"--{name.replace('_', '-')} must be a finite number > 0, got {v}")


def check_out_dir(out: str, flag: str = "--out") -> Path:
    """The output folder; ValueError for an empty name (which would write into the working
    directory without saying so)."""
    if not out or not out.strip():
        raise ValueError(f"{flag} is empty: give an output folder (use . for this one)")
    return Path(out)


def vectors(values: Sequence[float], dim: int, flag: str) -> tuple[tuple[float, ...], ...]:
    """A flat list of numbers as dim-vectors; ValueError unless its length is a multiple of dim."""
    if not values or len(values) % dim:
        raise ValueError(f"{flag} needs {dim} numbers for each state, got {len(values)} numbers")
    flat = [float(v) for v in values]
    if not all(math.isfinite(v) for v in flat):
        raise ValueError(f"{flag} needs finite numbers, got {list(values)}")
    return tuple(tuple(flat[i : i + dim]) for i in range(0, len(flat), dim))


#: Systems ``--system`` knows by name (a JSON file of ``system.to_dict()`` gives any other).
NAMED_SYSTEMS = ("rigid-body", "heavy-top")


def system_spec(spec: str) -> Any:
    """A system from a name in NAMED_SYSTEMS or a JSON file holding any system's
    ``to_dict()``."""
    import json

    from ..structures import system_from_dict
    from ..structures.lie_poisson import HeavyTop, RigidBody
    from ..untrusted import parsing

    if spec == "rigid-body":
        return RigidBody()
    if spec == "heavy-top":
        return HeavyTop()
    path = Path(spec)
    if not path.is_file():
        raise ValueError(
            f"{spec!r} is neither a known system ({', '.join(NAMED_SYSTEMS)}) nor a JSON file"
        )
    if path.stat().st_size > 1 << 20:
        raise ValueError(f"{spec} is over 1 MiB; a system description is a few lines of JSON")
    with parsing(f"--system {spec}"):
        data = json.loads(path.read_text(encoding="utf-8"))
        if not isinstance(data, dict):
            raise ValueError("must hold a JSON object (a system's to_dict())")
        return system_from_dict(data)


def sampling_flags(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--sampling",
        choices=["uniform", "scene"],
        help="training points uniform over the domain, or partly near the scene's orbits",
    )
    p.add_argument(
        "--sampling-fraction",
        dest="sampling_fraction",
        type=FRACTION,
        help="share of each batch near the orbits with --sampling scene (default 0.5)",
    )
    p.add_argument(
        "--sampling-noise",
        dest="sampling_noise",
        type=number(low=0.0, high=10.0),
        help="offset of an orbit point, relative to |μ| (default 0.02)",
    )


def scheduler_flag(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="run the independent jobs on Dask: 'local' (a LocalCluster, one single-threaded "
        "worker process per core) or a scheduler address such as tcp://host:8786 (default: "
        "serial, in this process; needs poisson_rs[distributed])",
    )


#: URL schemes of services that are not a Dask scheduler (its dashboard speaks HTTP).
_NOT_DASK = ("http://", "https://", "ws://", "wss://", "ftp://", "file://")


def check_scheduler(address: str | None) -> None:
    """ValueError for a ``--scheduler`` that is a web address (checked before any work)."""
    if address is not None and address.strip().lower().startswith(_NOT_DASK):
        raise ValueError(
            f"--scheduler {address!r} is a web address; a Dask scheduler listens on "
            "tcp://host:8786 (the dashboard's HTTP port is not the scheduler's)"
        )


@contextlib.contextmanager
def scheduler(address: str | None) -> Iterator[Any]:
    """The Dask client of ``--scheduler`` (None: serial). A web address, or any failure to
    connect, is one ValueError naming the address, never a traceback from the client."""
    from ..ensembles import scheduler_client

    check_scheduler(address)
    stack = contextlib.ExitStack()
    try:
        client = stack.enter_context(scheduler_client(address))
    except ValueError:
        raise
    except Exception as e:  # any failure to connect: one line
        raise ValueError(
            f"--scheduler {address!r}: cannot connect ({type(e).__name__}: {e})"
        ) from None
    with stack:
        yield client


def progress_printer(args: argparse.Namespace) -> Callable[[str], None] | None:
    """Progress lines on stderr, or None with ``--no-progress``."""
    if getattr(args, "no_progress", False):
        return None
    return lambda msg: print(f"  {msg}", file=sys.stderr, flush=True)

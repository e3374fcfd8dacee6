"""Command line: ``poisson-rs demo``, ``train``, ``models``, ``chart``, ``stability``, ``select``,
``sweep`` and ``learn``, for every system the package integrates.

Each subcommand is a module with ``add_parser(subparsers)`` and ``run(args)``; :data:`COMMANDS`
lists them, so a new subcommand is one more line there. Errors in what a user gave (a number, a
file, a scene) end in one line on stderr and exit status 2.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence
from types import ModuleType

from .common import Parser, UsageError

#: The subcommand modules, in the order ``--help`` lists them. A module that cannot be imported
#: because it does not exist (an optional part not installed) is left out.
COMMANDS = (
    "poisson_rs.cli.demo",
    "poisson_rs.cli.train",
    "poisson_rs.cli.models",
    "poisson_rs.cli.chart",
    "poisson_rs.cli.stability",
    "poisson_rs.cli.select",
    "poisson_rs.cli.sweep",
    "poisson_rs.learn.cli",
)


def _modules() -> list[ModuleType]:
    out = []
    for name in COMMANDS:
        try:
            out.append(importlib.import_module(name))
        except ModuleNotFoundError as e:
            if e.name is None or not name.startswith(e.name):
                raise  # a missing dependency inside an existing module is a real error
    return out


def _description() -> str:
    return "Learned and classical Poisson integrators: " + ", ".join(
        getattr(m, "NAME", m.__name__.rsplit(".", 1)[-1]) for m in _modules()
    )


def build_parser() -> Parser:
    """The parser of every subcommand; ``args.run`` is the chosen subcommand's ``run``."""
    p = Parser(prog="poisson-rs", description=_description())
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in _modules():
        sp = module.add_parser(sub)
        sp.set_defaults(run=module.run)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    from ..untrusted import InputError

    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = build_parser().parse_args(argv)
    except UsageError as e:
        print(_one_line(e), file=sys.stderr)
        return 2
    args.argv = argv
    try:
        return int(args.run(args))
    except (InputError, ValueError, FileNotFoundError, OverflowError) as e:
        print(f"poisson-rs {args.command}: {_one_line(e)}", file=sys.stderr)
        return 2
    except OSError as e:
        # A file that cannot be read or written (permissions, a full disk): one line, too.
        print(f"poisson-rs {args.command}: {_one_line(e)}", file=sys.stderr)
        return 2
    except MemoryError:
        print(f"poisson-rs {args.command}: out of memory", file=sys.stderr)
        return 2


def _one_line(e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return text if len(text) <= 500 else text[:499] + "…"


if __name__ == "__main__":
    sys.exit(main())

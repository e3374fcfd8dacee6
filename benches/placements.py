"""Fresh copies of a build's files, so that a bench times several placements of the same code.

The same extension, read from its original file and from a fresh copy of it, ran one kernel up to
1.3× apart on the same machine (docs/performance.md, "Closures out of line"): the bytes are the
same, the page-cache pages behind the code are not. A bench that times one file times one
placement, and a ratio between two builds can be a ratio between two placements. ``step_costs.py``
and ``peers.py`` therefore time each build from ``--copies`` fresh copies and report the median
over the copies with their range.
"""

from __future__ import annotations

import shutil
import statistics
from collections.abc import Sequence
from pathlib import Path


def fresh_copies(source: Path, n: int, into: Path) -> list[Path]:
    """``n`` copies of the file or package directory ``source``, as ``into/copy<i>/<name>``.

    Every file is read and written anew (no links, no ``copy_file_range``), so each copy is a new
    inode with its own page-cache pages; ``__pycache__`` folders are left out. Returns the copies'
    paths (of the file or the directory, as ``source`` is). ValueError for ``n < 1`` or a
    ``source`` that does not exist, before anything is written.
    """
    if n < 1:
        raise ValueError(f"copies: {n} asked, at least 1 needed")
    if not source.exists():
        raise ValueError(f"copies: {source} does not exist")
    out = []
    for i in range(n):
        target = into / f"copy{i}" / source.name
        target.parent.mkdir(parents=True, exist_ok=False)
        if source.is_dir():
            shutil.copytree(
                source, target, copy_function=_rewrite, ignore=shutil.ignore_patterns("__pycache__")
            )
        else:
            _rewrite(str(source), str(target))
        out.append(target)
    return out


def _rewrite(src: str, dst: str) -> str:
    """Copy the bytes through this process and keep the mode (an extension must stay readable)."""
    Path(dst).write_bytes(Path(src).read_bytes())
    shutil.copymode(src, dst)
    return dst


def summary(values: Sequence[float]) -> tuple[float, float, float]:
    """(median, min, max) of the copies' values; ValueError when there are none."""
    if not values:
        raise ValueError("summary: no values")
    return statistics.median(values), min(values), max(values)


def ratio_range(now: Sequence[float], before: Sequence[float]) -> tuple[float, float, float]:
    """now/before from two builds' per-copy values: the ratio of the medians, and the smallest
    and largest ratio of any copy of one to any copy of the other (what the placements allow)."""
    a, b = summary(now), summary(before)
    return a[0] / b[0], a[1] / b[2], a[2] / b[1]

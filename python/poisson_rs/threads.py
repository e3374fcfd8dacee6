"""How many threads a run may ask for: shared by ``train()`` and the command line, and light
enough to import before torch."""

from __future__ import annotations

import os

#: Most threads per core a run may ask for: beyond it threads only contend, and far beyond
#: (10⁴–10⁵) spawning them takes minutes or crashes the OpenMP runtime.
MAX_THREADS_PER_CORE = 4


def cpu_cores() -> int:
    """Cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


def max_threads() -> int:
    """The most threads a run accepts: ``MAX_THREADS_PER_CORE`` per core."""
    return MAX_THREADS_PER_CORE * max(cpu_cores(), os.cpu_count() or 1)

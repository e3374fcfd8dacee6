"""The memory one call may plan to take, for work done in Python (the DOP853 and exact
references): the core's estimate (``rust/memory.rs``, through ``_core.usable_memory``), so that
a Python-side rollout is refused where a Rust one of the same size is, with MemoryError before
any work."""

from __future__ import annotations

__all__ = ["MEMORY_SHARE", "budget_bytes", "check_fits", "usable_bytes"]

#: Fraction of the usable memory one call may plan to take (the rest is headroom for Python,
#: NumPy and the allocator), as in the core.
MEMORY_SHARE = 0.8

#: Cap on one call where no limit can be read, as in the core.
FALLBACK_MAX_BYTES = 16 << 30


def usable_bytes() -> int | None:
    """Bytes this process can still take: the least of MemAvailable, what RLIMIT_AS leaves of
    the address space and what the cgroup's limit leaves; None where none can be read (the
    core's own estimate, ``rust/memory.rs``)."""
    from . import _core

    return _core.usable_memory()


def budget_bytes() -> int:
    """What one call may plan to take: :data:`MEMORY_SHARE` of :func:`usable_bytes`."""
    usable = usable_bytes()
    return FALLBACK_MAX_BYTES if usable is None else int(usable * MEMORY_SHARE)


def check_fits(n_bytes: float, what: str, hint: str) -> None:
    """MemoryError, naming ``what`` and the size, when a plan of ``n_bytes`` does not fit in
    :func:`budget_bytes`; ``hint`` says how to need less."""
    limit = budget_bytes()
    if n_bytes > limit:
        raise MemoryError(
            f"{what} needs about {_size(n_bytes)} but only {_size(limit)} can be used now (the "
            f"least of the available memory, the address-space limit and the cgroup limit); {hint}"
        )


def _size(n_bytes: float) -> str:
    """Bytes in GiB, or MiB below a tenth of a GiB (so that a small size is not "0.00 GiB")."""
    if n_bytes >= 2**30 / 10:
        return f"{n_bytes / 2**30:.2f} GiB"
    return f"{n_bytes / 2**20:.2f} MiB"

"""The memory one call may plan to take, for work done in Python (the DOP853 and exact
references): the same estimate as the core's (``rust/memory.rs``), so that a Python-side rollout
is refused where a Rust one of the same size is, with MemoryError before any work."""

from __future__ import annotations

import resource
from pathlib import Path

__all__ = ["MEMORY_SHARE", "budget_bytes", "check_fits", "usable_bytes"]

#: Fraction of the usable memory one call may plan to take (the rest is headroom for Python,
#: NumPy and the allocator), as in the core.
MEMORY_SHARE = 0.8

#: Cap on one call where no limit can be read, as in the core.
FALLBACK_MAX_BYTES = 16 << 30


def _proc_kib(text: str, key: str) -> int | None:
    """A "Key:   value kB" line of a /proc file, in bytes."""
    for line in text.splitlines():
        if line.startswith(key):
            fields = line[len(key) :].split()
            return int(fields[0]) * 1024 if fields and fields[0].isdigit() else None
    return None


def _read(path: Path) -> str | None:
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError):
        return None


def _number(text: str | None) -> int | None:
    """An integer file's value; None for "max" (no limit) or anything unreadable."""
    if text is None:
        return None
    text = text.strip()
    return int(text) if text.isdigit() else None


def _mem_available() -> int | None:
    text = _read(Path("/proc/meminfo"))
    return None if text is None else _proc_kib(text, "MemAvailable:")


def _address_space_left() -> int | None:
    """The soft RLIMIT_AS minus the address space already mapped (VmSize); None when
    unlimited or unreadable."""
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY or soft < 0:
        return None
    status = _read(Path("/proc/self/status"))
    used = (_proc_kib(status, "VmSize:") if status is not None else None) or 0
    return max(int(soft) - used, 0)


def _cgroup_left(root: Path = Path("/sys/fs/cgroup")) -> int | None:
    """The tightest cgroup limit minus its usage: v2 (``memory.max``, ``memory.current``, the
    process's cgroup and its ancestors) or v1 (``memory.limit_in_bytes``); None when
    unlimited or unreadable."""
    own_text = _read(Path("/proc/self/cgroup")) or ""
    own = next((ln[3:].strip() for ln in own_text.splitlines() if ln.startswith("0::")), None)
    if own is not None:
        best: int | None = None
        found = False
        path = root / own.lstrip("/")
        while True:
            max_text = _read(path / "memory.max")
            if max_text is not None:
                found = True
                limit = _number(max_text)
                if limit is not None:
                    left = max(limit - (_number(_read(path / "memory.current")) or 0), 0)
                    best = left if best is None else min(best, left)
            if path == root or path.parent == path:
                break
            path = path.parent
        if found:
            return best
    limit = _number(_read(root / "memory" / "memory.limit_in_bytes"))
    if limit is None or limit >= 1 << 62:  # v1 writes a huge number for "no limit"
        return None
    used = _number(_read(root / "memory" / "memory.usage_in_bytes")) or 0
    return max(limit - used, 0)


def usable_bytes() -> int | None:
    """Bytes this process can still take: the least of MemAvailable, what RLIMIT_AS leaves of
    the address space and what the cgroup's limit leaves; None where none can be read."""
    known = [v for v in (_mem_available(), _address_space_left(), _cgroup_left()) if v is not None]
    return min(known) if known else None


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

"""Safe file output and input: every writer in the package goes through :func:`atomic_write_bytes`,
every file it reads by path through :func:`check_input_file`.

A writer replaces only a regular file or creates a new one: a device (``/dev/null``), a FIFO, a
symbolic link or a directory at the target is refused with a ValueError before anything is written,
and before any long computation when the caller checks its outputs up front
(:func:`check_output_path`).
"""

from __future__ import annotations

import os
import secrets
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import Literal


def _describe(mode: int) -> str:
    """What a non-regular file is, for the messages."""
    for test, what in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISLNK, "a symbolic link"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return what
    return "not a regular file"


def check_output_path(
    path: str | os.PathLike[str], *, kind: Literal["file", "dir"] = "file"
) -> Path:
    """Checks that ``path`` can be written as ``kind`` without replacing anything else; returns it.

    "file": ``path`` is absent or a regular file (not a symbolic link, FIFO, device or directory).
    "dir": ``path`` is absent or a directory (a link to one is fine: files go inside it).
    Either way the nearest existing ancestor must be a writable directory (missing folders are
    created by the writer). Raises ValueError naming the path and the problem.
    """
    if kind not in ("file", "dir"):
        raise ValueError(f"kind must be 'file' or 'dir', got {kind!r}")
    path = Path(path)
    if str(path) == "" or path.name in ("", ".", ".."):
        if kind == "file":
            raise ValueError(f"output {str(path)!r} is not a file name")
    try:
        st = os.lstat(path)
    except (FileNotFoundError, NotADirectoryError):  # the latter: a parent is a file
        st = None
    if st is not None:
        if kind == "file" and not stat.S_ISREG(st.st_mode):
            raise ValueError(
                f"output {path} is {_describe(st.st_mode)}; only a regular file or a new path "
                "is written"
            )
        if kind == "dir" and not path.is_dir():
            raise ValueError(f"output folder {path} exists and is not a directory")
        if kind == "dir":
            return path
    # The nearest existing ancestor decides whether the missing folders can be made.
    parent = path.parent
    while not os.path.lexists(parent) and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ValueError(f"cannot write {path}: {parent} is not a directory")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise ValueError(f"cannot write {path}: directory {parent} is not writable")
    return path


def check_outputs(folder: str | os.PathLike[str], names: Iterable[str]) -> Path:
    """Checks an output folder and the files ``names`` to be written in it (see
    :func:`check_output_path`); returns the folder. Meant to run before the work."""
    folder = check_output_path(folder, kind="dir")
    for name in names:
        check_output_path(folder / name)
    return folder


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Writes ``data`` to ``path`` atomically: readers see the old file or the new one, never a
    half-written one. Creates missing parent folders; refuses to replace anything but a regular
    file (ValueError). Returns the path."""
    path = check_output_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    # O_EXCL: the temporary file is new, never a link someone placed there.
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        # Checked again right before the rename: the target may have changed while writing.
        check_output_path(path)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def check_input_file(path: str | os.PathLike[str], *, max_bytes: int, what: str = "file") -> Path:
    """Checks that ``path`` is a regular file (after links) of at most ``max_bytes`` before it is
    read: a FIFO would block the reader, a device such as /dev/zero would fill the memory.
    Raises FileNotFoundError when absent, ValueError otherwise; returns the path."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise FileNotFoundError(f"no {what} at {path}") from None
    if not stat.S_ISREG(st.st_mode):
        raise ValueError(f"{what} {path} is {_describe(st.st_mode)}, not a regular file")
    if st.st_size > max_bytes:
        raise ValueError(
            f"{what} {path} holds {st.st_size} bytes, more than the {max_bytes} allowed"
        )
    return path

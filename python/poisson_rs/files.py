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


def describe_mode(mode: int) -> str:
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
    except OSError as exc:  # a name too long, a loop of links, no permission on a parent
        raise ValueError(f"cannot write {path}: {exc.strerror or exc}") from None
    if st is not None:
        if kind == "file" and not stat.S_ISREG(st.st_mode):
            raise ValueError(
                f"output {path} is {describe_mode(st.st_mode)}; only a regular file or a new path "
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


#: Longest file name where the file system cannot say (Linux and most others: 255 bytes).
_NAME_MAX = 255


def _name_max(folder: Path) -> int:
    try:
        return int(os.pathconf(folder, "PC_NAME_MAX"))
    except (OSError, ValueError):
        return _NAME_MAX


def temporary_name(path: str | os.PathLike[str], tag: str = "tmp") -> Path:
    """A fresh name beside ``path`` for a temporary file or folder: hidden, random, and never
    longer than the file system allows, however long ``path``'s own name is (a 252-byte target
    is legal; ``.<name>.<pid>.<random>.tmp`` would not be). The target's name is kept as far as
    it fits, cut at a character boundary."""
    path = Path(path)
    suffix = f".{os.getpid()}.{secrets.token_hex(4)}.{tag}"
    room = min(_name_max(path.parent if str(path.parent) else Path(".")), _NAME_MAX)
    room -= len(os.fsencode(suffix)) + 1  # the leading dot
    stem = os.fsencode(path.name)[: max(room, 0)]
    text = stem.decode("utf-8", errors="ignore") if stem else ""
    while len(os.fsencode(text)) > room:  # a name that is not UTF-8 (surrogate escapes)
        text = text[:-1]
    return path.with_name(f".{text}{suffix}")


def _fsync_dir(folder: Path) -> None:
    """Makes a rename in ``folder`` durable (best effort: some file systems refuse)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def probe_writable(path: str | os.PathLike[str], *, kind: Literal["file", "dir"] = "file") -> Path:
    """Checks, before the work, that an output can really be written where ``path`` says: beyond
    :func:`check_output_path`, it creates, writes, syncs and removes a real temporary file with
    the name the writer will use (so a name too long for the file system, a read-only mount, a
    full quota on the first block or a missing permission show up now, not after an hour of
    training). Folders it had to create are removed again. Raises ValueError naming the path and
    the problem; returns the path."""
    path = check_output_path(path, kind=kind)
    folder = path if kind == "dir" else path.parent
    probe_target = folder / ".probe" if kind == "dir" else path
    created: list[Path] = []
    missing = folder
    while not os.path.lexists(missing) and missing != missing.parent:
        created.append(missing)
        missing = missing.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        tmp = temporary_name(probe_target, "probe")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        try:
            os.write(fd, b"\0")
            os.fsync(fd)
        finally:
            os.close(fd)
            tmp.unlink(missing_ok=True)
    except OSError as exc:
        raise ValueError(f"cannot write {path}: {exc.strerror or exc}") from None
    finally:
        for d in created:
            try:
                d.rmdir()
            except OSError:
                pass
    return path


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes, *, replace: bool = True) -> Path:
    """Writes ``data`` to ``path`` atomically: readers see the old file or the new one, never a
    half-written one. Creates missing parent folders; refuses to replace anything but a regular
    file (ValueError). With ``replace=False`` an existing file is not replaced either, even one
    that appeared while the caller worked: the new file is linked in place only where nothing is
    (ValueError otherwise, the file there untouched). Returns the path.

    The data is written to a temporary file beside the target (a name that always fits, see
    :func:`temporary_name`), synced, then renamed over the target, and the folder is synced.
    A replaced file keeps its permission bits (a 0600 file stays 0600; a new one gets 0666 less
    the umask) and, where allowed, its owner and group. Hard links: the rename gives the path a
    new file, so other names linked to the old one keep the old contents; atomicity is chosen
    over writing in place, which a crash could leave half-written."""
    path = check_output_path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        old = os.stat(path)
    except FileNotFoundError:
        old = None
    # O_EXCL: the temporary file is new, never a link someone placed there.
    tmp = temporary_name(path)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666 if old is None else 0o600)
    try:
        with os.fdopen(fd, "wb") as f:
            if old is not None:
                os.fchmod(f.fileno(), stat.S_IMODE(old.st_mode))
                try:
                    os.fchown(f.fileno(), old.st_uid, old.st_gid)
                except OSError:
                    pass  # not ours to give away: the new file stays the writer's
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        # Checked again right before the rename: the target may have changed while writing.
        check_output_path(path)
        if replace:
            os.replace(tmp, path)
        else:
            _link_new(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync_dir(path.parent)
    return path


def _link_new(tmp: Path, path: Path) -> None:
    """Moves ``tmp`` to ``path`` only where nothing is at ``path``: a hard link fails, atomically,
    when the name exists (a rename would replace it)."""
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise ValueError(
            f"output {path} exists (it appeared while the work ran); not replaced"
        ) from None
    except OSError:
        # A file system without hard links: the check and the rename are then two steps.
        if os.path.lexists(path):
            raise ValueError(
                f"output {path} exists (it appeared while the work ran); not replaced"
            ) from None
        os.replace(tmp, path)
        return
    tmp.unlink(missing_ok=True)


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
        raise ValueError(f"{what} {path} is {describe_mode(st.st_mode)}, not a regular file")
    if st.st_size > max_bytes:
        raise ValueError(
            f"{what} {path} holds {st.st_size} bytes, more than the {max_bytes} allowed"
        )
    return path


def read_input_bytes(path: str | os.PathLike[str], *, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of the regular file ``path`` (after links), at most ``max_bytes`` of them.

    Checked on the open file itself, not on the name: the file is opened without blocking (a
    FIFO put there after a check would otherwise block the open), then its status is read from
    the open descriptor, and at most ``max_bytes`` + 1 bytes are read (a file that grows past the
    cap while read is refused too). Raises FileNotFoundError when absent, ValueError for a FIFO,
    a device, a directory or a file over the cap."""
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except FileNotFoundError:
        raise FileNotFoundError(f"no {what} at {path}") from None
    except OSError as exc:
        raise ValueError(f"{what} {path} cannot be read: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise ValueError(f"{what} {path} is {describe_mode(st.st_mode)}, not a regular file")
        if st.st_size > max_bytes:
            raise ValueError(
                f"{what} {path} holds {st.st_size} bytes, more than the {max_bytes} allowed"
            )
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        chunks: list[bytes] = []
        left = max_bytes + 1
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 24))
            if not chunk:
                break
            chunks.append(chunk)
            left -= len(chunk)
    finally:
        os.close(fd)
    if left <= 0:
        raise ValueError(f"{what} {path} holds more than the {max_bytes} bytes allowed")
    return b"".join(chunks)

"""Writing files so that a reader never sees half of one, and no input is overwritten."""

from __future__ import annotations

import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, BinaryIO

from .errors import StochlapError


class NotARegularFileError(StochlapError, OSError):
    """A path that names something other than a regular file (a FIFO, a device, a socket, a
    directory): writing a file in its place would delete that node, so it is refused.
    ``filename`` is the path; setting it does not change the message.
    """

    def __init__(self, path: str | os.PathLike, kind: str, action: str = "replace"):
        path = Path(path)
        self.kind, self.action = kind, action
        through = f" (a link to {os.path.realpath(path)})" if path.is_symlink() else ""
        self.message = f"{path}{through} is {kind}, not a regular file; refusing to {action} it"
        super().__init__(self.message)
        self.filename = str(path)

    def __str__(self) -> str:
        return self.message

    def __reduce__(self):  # pickled across processes: rebuilt from what __init__ takes
        return type(self), (self.filename, self.kind, self.action)


def node_kind(path: str | os.PathLike) -> str | None:
    """What ``path`` names when that is not a regular file (``"a FIFO"``, ``"a directory"``,
    ...); ``None`` for a regular file, a symbolic link to one, or nothing that can be looked
    at."""
    try:
        return _kind(os.stat(path).st_mode)  # through symbolic links
    except (OSError, ValueError):
        return None


@contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; on success it replaces ``path`` in one
    step (``os.replace``), on any error it is removed and ``path`` is left as it was.

    A symbolic link is written through. An existing file keeps its permission bits (and its
    owner and group where this process may set them). A path that is not a regular file is
    refused, before the write and again just before the replacement.

    Raises:
        NotARegularFileError: ``path`` exists and is not a regular file (nothing is written).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    kind = node_kind(path)
    if kind is not None:
        raise NotARegularFileError(path, kind)
    target = Path(os.path.realpath(path))
    handle, temporary = tempfile.mkstemp(
        dir=target.parent, prefix=f".{target.name}.", suffix=".tmp"
    )
    try:
        with os.fdopen(handle, mode) as file:
            yield file
            file.flush()
            os.fsync(file.fileno())
        # Looked at again now: a node may have taken the name while the content was written.
        existing = _stat_or_none(target)
        kind = None if existing is None else _kind(existing.st_mode)
        if kind is not None:
            raise NotARegularFileError(path, kind)
        _take_mode_and_owner(temporary, existing)
        os.replace(temporary, target)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Whether two paths name the same file (resolving links and ``..``; ``False`` if either
    does not exist yet and they differ as resolved paths)."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def open_regular(path: str | os.PathLike) -> BinaryIO | None:
    """``path`` open for binary reading if it is a regular file after following links; ``None``
    if nothing is there. A FIFO would block its reader and opening a device can act on it, so
    the file is examined before the open, which cannot wait (``O_NONBLOCK``), and after it.

    Raises:
        NotARegularFileError: something else is there.
        OSError: it cannot be examined or opened.
    """
    existing = _stat_or_none(Path(path))
    if existing is None:
        return None
    kind = _kind(existing.st_mode)
    if kind is not None:
        raise NotARegularFileError(path, kind, "read")
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    descriptor = os.open(path, flags | getattr(os, "O_BINARY", 0))
    kind = _kind(os.fstat(descriptor).st_mode)
    if kind is not None:
        os.close(descriptor)
        raise NotARegularFileError(path, kind, "read")
    return os.fdopen(descriptor, "rb")


def _kind(mode: int) -> str | None:
    """``None`` for a regular file, else what the file of ``st_mode`` ``mode`` is."""
    if stat.S_ISREG(mode):
        return None
    for test, kind in (
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return kind
    return "a special file"


def _stat_or_none(path: Path) -> os.stat_result | None:
    try:
        return os.stat(path)
    except FileNotFoundError:
        return None


def _take_mode_and_owner(temporary: str, existing: os.stat_result | None) -> None:
    """Give the temporary file the permissions the replaced file had (a new file: those
    ``open`` would give it under the umask), so that replacing does not widen a 0600 file."""
    if existing is None:
        os.chmod(temporary, 0o666 & ~_umask())
        return
    owner = (existing.st_uid, existing.st_gid)
    created = os.stat(temporary)
    if hasattr(os, "chown") and owner != (created.st_uid, created.st_gid):
        try:
            os.chown(temporary, *owner)
        except OSError:  # only root may give a file away; the mode is kept regardless
            pass
    # After chown, which clears the set-user-ID and set-group-ID bits.
    os.chmod(temporary, stat.S_IMODE(existing.st_mode))


def _umask() -> int:
    """The process's umask, read from Linux's ``/proc/self/status``: ``os.umask`` can only set
    it, process-wide, for every thread. Elsewhere it is set to the most restrictive value for
    that moment."""
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    current = os.umask(0o077)
    os.umask(current)
    return current

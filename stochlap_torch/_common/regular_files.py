"""Opening a file only when it is a regular one: a FIFO blocks its reader until a writer comes
(forever, for a cache entry), and opening a device can act on it."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

__all__ = ["NotRegularFile", "open_regular", "special_kind"]


class NotRegularFile(OSError):
    """Something other than a regular file is at a path; the message says what
    (:func:`special_kind`)."""


_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def _kind(mode: int) -> str | None:
    """``None`` for a regular file, else what the file of ``st_mode`` ``mode`` is."""
    if stat.S_ISREG(mode):
        return None
    return next((name for test, name in _KINDS if test(mode)), "a special file")


def special_kind(path: str | os.PathLike) -> str | None:
    """What is at ``path`` after following links when it is not a regular file (``"a FIFO"``,
    ``"a folder"``, ...); ``None`` for a regular file, nothing, a dangling link, or a path that
    cannot be examined."""
    try:
        return _kind(os.stat(path).st_mode)
    except OSError:
        return None


def open_regular(path: str | os.PathLike) -> BinaryIO | None:
    """``path`` open for binary reading if it is a regular file after following links; ``None``
    if nothing is there.

    The file is examined before it is opened, so a FIFO or device is never opened; the open
    itself cannot wait (``O_NONBLOCK``) and is examined again, for a file swapped in between.

    Raises:
        NotRegularFile: something else is there.
        OSError: it cannot be examined or opened.
    """
    path = Path(path)
    try:
        kind = _kind(os.stat(path).st_mode)
    except FileNotFoundError:
        return None
    if kind is not None:
        raise NotRegularFile(kind)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0)
    descriptor = os.open(path, flags | getattr(os, "O_BINARY", 0))
    kind = _kind(os.fstat(descriptor).st_mode)
    if kind is not None:
        os.close(descriptor)
        raise NotRegularFile(kind)
    return os.fdopen(descriptor, "rb")

"""The command line's own error types (the library's are :mod:`stochlap_torch._common.errors`),
and the signal handlers that turn SIGTERM and SIGHUP into an exception while a command runs."""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

#: The signals that end a command by :class:`Terminated` (SIGINT already raises
#: ``KeyboardInterrupt``); SIGHUP does not exist on Windows.
TERMINATING = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


class CommandError(Exception):
    """A problem with the user's input, reported as one line and exit status 2."""


class UsageError(CommandError):
    """A command line argparse rejects (unknown option, bad value, missing argument)."""


class Terminated(BaseException):
    """SIGTERM or SIGHUP received while a command ran (exit status ``128 + signum``); a
    ``BaseException`` like ``KeyboardInterrupt``: ``except Exception`` does not swallow it, and
    every cleanup on the way out runs (a file being written removes its temporary)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)

    @property
    def name(self) -> str:
        """``"SIGTERM"``, ``"SIGHUP"``."""
        return signal.Signals(self.signum).name


@contextmanager
def terminate_by_exception() -> Iterator[None]:
    """While the block runs, SIGTERM and SIGHUP raise :class:`Terminated` in the main thread:
    only signals at their default action (not one ``nohup`` ignores or an embedding program
    handles), put back on exit; a second signal while the first unwinds is ignored, so that
    cleanup is not cut short. Nothing outside the main thread (no handlers there)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    taken = [signum for signum in TERMINATING if signal.getsignal(signum) is signal.SIG_DFL]
    raised = []

    def raise_terminated(signum, frame) -> None:
        if not raised:
            raised.append(signum)
            raise Terminated(signum)

    for signum in taken:
        signal.signal(signum, raise_terminated)
    try:
        yield
    finally:
        for signum in taken:
            signal.signal(signum, signal.SIG_DFL)

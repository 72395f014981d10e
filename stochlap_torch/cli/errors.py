"""The command line's own error types (the library's are :mod:`stochlap_torch._common.errors`)."""

from __future__ import annotations

__all__ = ["CommandError", "UsageError"]


class CommandError(Exception):
    """A problem with the user's input, reported as one line and exit status 2."""


class UsageError(CommandError):
    """A command line argparse rejects (unknown option, bad value, missing argument)."""

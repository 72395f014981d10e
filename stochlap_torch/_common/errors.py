"""The library's exception types: every error it raises on purpose is a :class:`StochlapError`,
and also the built-in type a caller would expect (``ValueError`` for bad input, ``ImportError``
for a missing optional dependency). The command line catches :class:`StochlapError` only, so a
bug in the library is never reported as a user mistake.
"""

from __future__ import annotations


class StochlapError(Exception):
    """Base class of the errors the library raises on purpose."""


class MeshError(StochlapError, ValueError):
    """A mesh that cannot be processed; the message names the problem and where it is."""


class ParameterError(StochlapError, ValueError):
    """A parameter outside its documented range or of the wrong type; the message names it."""


class FileFormatError(StochlapError, ValueError):
    """A data file that cannot be read (ground-truth marks, feature files: the message names
    the file), or values a file format cannot hold; an unreadable mesh file is a MeshError."""


class UnsupportedInputError(StochlapError, TypeError):
    """An input of a type or dtype the library does not handle (e.g. float16, complex)."""


class MissingDependencyError(StochlapError, ImportError):
    """An optional dependency is not installed; the message names the extra that has it."""


class CacheError(StochlapError, OSError):
    """A cache that cannot be used (its folder cannot be created or written)."""


class DistributedError(StochlapError, RuntimeError):
    """The ranks of a distributed run disagree on the mesh or the parameters."""

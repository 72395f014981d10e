"""What the subcommands share: options, one-line messages, progress, the mesh, pictures.

Nothing here imports torch or the library at module level (``stochlap --help`` stays fast);
the helpers that need them import them when called.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

__all__ = [
    "PROG",
    "VIZ_HINT",
    "CommandError",
    "Parser",
    "Progress",
    "UsageError",
    "add_common_options",
    "add_compute_options",
    "add_mesh_argument",
    "add_picture_options",
    "load_mesh_arg",
    "mesh_path",
    "one_line",
    "say",
    "want_picture",
    "warn",
]

PROG = "stochlap"
VIZ_HINT = 'pip install "stochlap_torch[viz]"'
#: ``--up`` values: the signed axes of the mesh file (``--up -y`` works as well as ``--up=-y``).
UP_CHOICES = ("x", "y", "z", "-x", "-y", "-z")
DTYPES = ("float32", "float64")


class CommandError(Exception):
    """A problem with the user's input, reported as one line and exit status 2."""


class UsageError(CommandError):
    """A command line argparse rejects (unknown option, bad value, missing argument)."""


class Parser(argparse.ArgumentParser):
    """``argparse.ArgumentParser`` whose usage errors raise :class:`UsageError` (printed as one
    line by ``main``) instead of printing the usage and exiting."""

    def error(self, message: str):
        raise UsageError(f"{message} (see '{self.prog} --help')")


def one_line(message: object) -> str:
    """``message`` as a single line (runs of whitespace, newlines included, become a space)."""
    return " ".join(str(message).split())


def warn(message: str) -> None:
    """Print ``stochlap: warning: <message>`` as one line on stderr."""
    sys.stderr.write(f"{PROG}: warning: {one_line(message)}\n")
    sys.stderr.flush()


def say(args, message: str) -> None:
    """Print a summary line on stdout unless ``--quiet``."""
    if not args.quiet:
        print(message, flush=True)


# --------------------------------------------------------------------------------------------
# Option types: bad values are usage errors naming the option, raised before any work.


def _number(text: str, kind):
    try:
        value = kind(text)
    except ValueError:
        name = "an integer" if kind is int else "a number"
        raise argparse.ArgumentTypeError(f"expected {name}, got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


def num_scales(text: str) -> int:
    value = _number(text, int)
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be an integer >= 2, got {text!r}")
    return value


def open_unit(text: str) -> float:
    """A float in the open interval (0, 1)."""
    value = _number(text, float)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"must lie in the open interval (0, 1), got {text!r}")
    return value


def closed_unit(text: str) -> float:
    value = _number(text, float)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1], got {text!r}")
    return value


def positive_float(text: str) -> float:
    value = _number(text, float)
    if not value > 0.0:
        raise argparse.ArgumentTypeError(f"must be positive, got {text!r}")
    return value


def non_negative_float(text: str) -> float:
    value = _number(text, float)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text!r}")
    return value


# --------------------------------------------------------------------------------------------
# Options shared by the subcommands


def add_common_options(parser: argparse.ArgumentParser, default) -> None:
    """``--threads``, ``-v``, ``-q``; accepted before and after the subcommand name."""
    parser.add_argument(
        "--threads",
        type=positive_int,
        metavar="N",
        default=default,
        help="CPU threads (at most the CPUs this process may use)",
    )
    parser.add_argument(
        "-v", "--verbose", action="store_true", default=default, help="log library messages"
    )
    parser.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default,
        help="print only errors and warnings (no progress, no summary)",
    )


def add_mesh_argument(parser: argparse.ArgumentParser) -> None:
    """The optional ``MESH`` (default: the bundled cow) and ``--merge-seams``."""
    parser.add_argument(
        "mesh",
        nargs="?",
        metavar="MESH",
        help="triangle mesh file (OBJ, OFF, PLY, STL, ...); default: the bundled 'spot' cow",
    )
    parser.add_argument(
        "--merge-seams",
        action="store_true",
        help="merge vertices at identical positions (texture/normal seams) before processing",
    )


def add_compute_options(parser: argparse.ArgumentParser, dtype: bool = True) -> None:
    """``-K``, ``--threshold`` and (optionally) ``--dtype``."""
    parser.add_argument(
        "-K",
        "--num-scales",
        type=num_scales,
        default=8,
        metavar="K",
        help="number of scales K >= 2 (default: 8)",
    )
    parser.add_argument(
        "--threshold",
        type=open_unit,
        default=1e-3,
        metavar="LAMBDA",
        help="precision lambda in (0, 1): smaller operator entries are dropped (default: 1e-3)",
    )
    if dtype:
        parser.add_argument(
            "--dtype",
            choices=DTYPES,
            default="float64",
            help="floating-point type of the computation (default: float64)",
        )


def add_picture_options(parser: argparse.ArgumentParser, png: bool = True) -> None:
    """``--png PNG`` (optional) / ``--no-png`` and ``--up``."""
    group = parser.add_mutually_exclusive_group()
    if png:
        group.add_argument("--png", metavar="PNG", help="picture file (default: derived name)")
    group.add_argument("--no-png", action="store_true", help="do not draw a picture")
    parser.add_argument(
        "--up",
        choices=UP_CHOICES,
        default=None,
        metavar="AXIS",
        help="vertical axis of the mesh file in pictures: x, y, z, -x, -y or -z (default: "
        "y, or the middle extent for a flat mesh, turned over when the flat base of the mesh "
        "is at the top)",
    )


# --------------------------------------------------------------------------------------------
# Progress, the mesh, pictures


class Progress:
    """``progress(k, K)`` callback: a ``scale k/K`` line, redrawn with ``\\r`` on a terminal,
    one line per scale otherwise; silent with ``quiet``."""

    def __init__(self, label: str, quiet: bool = False, stream=None):
        self.label = label
        self.quiet = quiet
        self.stream = sys.stderr if stream is None else stream
        self.start = time.perf_counter()
        self.width = 0
        try:
            self.tty = bool(self.stream.isatty())
        except (AttributeError, ValueError):
            self.tty = False

    def __call__(self, k: int, num_scales: int) -> None:
        if self.quiet:
            return
        elapsed = time.perf_counter() - self.start
        text = f"{self.label}: scale {k}/{num_scales} ({elapsed:.1f} s)"
        if self.tty:
            end = "\n" if k >= num_scales else ""
            self.width = max(self.width, len(text))
            self.stream.write(f"\r{text:<{self.width}}{end}")
        else:
            self.stream.write(f"{PROG}: {text}\n")
        self.stream.flush()


def mesh_path(given: str | None) -> Path:
    """The ``MESH`` argument, or the bundled cow."""
    if given is not None:
        return Path(given)
    from ..mesh import bundled_mesh_path

    return bundled_mesh_path("spot")


def load_mesh_arg(args, path: Path):
    """Load ``path`` with ``--merge-seams`` in ``--dtype`` (checked in that dtype), and say so."""
    import torch

    from ..mesh import load_mesh

    dtype = getattr(torch, getattr(args, "dtype", "float64"))
    mesh = load_mesh(path, merge_seams=getattr(args, "merge_seams", False), dtype=dtype)
    say(args, f"{path.name}: {mesh.num_vertices} vertices, {mesh.num_faces} faces")
    return mesh


def want_picture(args) -> bool:
    """Whether to draw the picture: not with ``--no-png``; without matplotlib an explicit
    ``--png`` is an error and the default picture is skipped with a warning."""
    if getattr(args, "no_png", False):
        return False
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        if getattr(args, "png", None):
            raise CommandError(f"--png needs matplotlib: {VIZ_HINT}, or pass --no-png") from None
        warn(
            f"matplotlib is not installed, so no picture is drawn ({VIZ_HINT}; "
            "--no-png silences this)"
        )
        return False
    return True

"""What the subcommands share: one-line messages, progress, the mesh, pictures (torch and the
library imported when called, so that ``stochlap --help`` stays fast)."""

from __future__ import annotations

import argparse
import inspect
import logging
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from .errors import CommandError, UsageError

PROG = "stochlap"
VIZ_HINT = 'pip install "stochlap_torch[viz]"'


class Parser(argparse.ArgumentParser):
    """Usage errors raise :class:`UsageError` (one line, by ``main``), not print and exit."""

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


def compute_settings(args) -> str:
    """``variant=.., K=.., threshold=..`` (the threshold where it applies), from
    ``args.params`` (the resolved parameters) when the command has ``--variant``."""
    params = getattr(args, "params", None)
    if params is None:  # a paper-only command: -K and --threshold as given
        return f"K={args.num_scales}, threshold={args.threshold:g}"
    if args.variant == "robust":
        return f"variant=robust, K={params.num_scales}"
    return f"variant={args.variant}, K={params.num_scales}, threshold={params.threshold:g}"


@contextmanager
def usage_errors() -> Iterator[None]:
    """A :class:`~stochlap_torch.ParameterError` of the block (an option checked by the
    library before any work) as a :class:`UsageError`."""
    from .._common.errors import ParameterError

    try:
        yield
    except ParameterError as error:
        raise UsageError(str(error)) from None


def is_terminal(stream) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # no isatty, or closed
        return False


class _OneLineFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return one_line(super().format(record))


@contextmanager
def messages(verbose: bool) -> Iterator[None]:
    """Library log records (INFO with ``verbose``) and warnings on stderr, one line each and
    each distinct warning once, for the run of a command (or a worker process's life)."""
    library = logging.getLogger("stochlap_torch")
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(_OneLineFormatter(f"{PROG}: %(name)s: %(message)s"))
    level = library.level
    library.addHandler(handler)
    library.setLevel(logging.INFO if verbose else logging.WARNING)
    shown: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = one_line(message)
        if not category.__module__.startswith("stochlap_torch"):
            text = f"{category.__name__}: {text}"
        if text not in shown:  # each distinct warning once per run
            shown.add(text)
            warn(text)

    try:
        with warnings.catch_warnings():
            if not sys.warnoptions:  # python -W ... takes precedence
                warnings.simplefilter("default")
            warnings.showwarning = show
            yield
    finally:
        library.removeHandler(handler)
        library.setLevel(level)


class Progress:
    """``progress(k, K)`` callback: a ``scale k/K`` line, redrawn with ``\\r`` on a terminal,
    one line per scale otherwise; silent with ``quiet``."""

    def __init__(self, label: str, quiet: bool = False, stream=None):
        self.label = label
        self.quiet = quiet
        self.stream = sys.stderr if stream is None else stream
        self.start = time.perf_counter()
        self.width = 0
        self.tty = is_terminal(self.stream)

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
        hint = f"{VIZ_HINT}; --no-png silences this"
        warn(f"matplotlib is not installed, so no picture is drawn ({hint})")
        return False
    return True


def open_mesh(
    args, path: Path, outputs: Sequence[tuple[str, Path]], picture: tuple[str, Path]
) -> tuple[object, Path | None]:
    """Before a mesh command computes: refuse ``(option, path)`` outputs that would overwrite
    the mesh or each other (the picture too, drawn or not), decide on the picture, load the
    mesh. Returns the mesh and the picture's path (``None``: no picture)."""
    from .outputs import check_outputs

    check_outputs([("mesh", path)], [*outputs, picture])
    draw = want_picture(args)
    mesh = load_mesh_arg(args, path)
    plys = [output for _, output in outputs if Path(output).suffix.lower() == ".ply"]
    if plys:  # refuse before computing what could not be written
        from ..mesh.io import check_ply_positions

        check_ply_positions(mesh.vertices.detach().cpu().numpy(), plys[0])
    return mesh, picture[1] if draw else None


def open_mesh_and_outputs(
    args, name: str, extension: str
) -> tuple[Path, object, Path, Path | None]:
    """:func:`open_mesh` for a command that writes ``-o`` (default
    ``<stem>_<name>.<extension>``) and ``--png`` (default ``<stem>_<name>.png``); returns the
    ``MESH`` path, the mesh, the ``-o`` path, and the picture's path or ``None``."""
    from .outputs import default_output

    path = mesh_path(args.mesh)
    out_path = default_output(args.output, path, name, extension)
    png_path = default_output(args.png, path, name, "png")
    mesh, png_path = open_mesh(args, path, [("-o", out_path)], ("--png", png_path))
    return path, mesh, out_path, png_path


def draw_picture(args, path: Path | str | None, render: Callable, *arrays, **options) -> None:
    """Draw ``render(*arrays, path, **options)`` with the picture options given and say
    ``wrote <path>``; nothing when ``path`` is ``None``."""
    if path is not None:
        options.update(picture_options(args, render))
        render(*arrays, path, **options)
        say(args, f"wrote {path}")


def picture_options(args, render: Callable) -> dict:
    """The keyword arguments of ``--dpi``, ``--cmap``, ``--views`` (those given) and
    ``--no-title`` (``title=None``) for ``render``; an option ``render`` cannot use is
    refused, never ignored."""
    given = {name: getattr(args, name, None) for name in ("dpi", "cmap", "views")}
    chosen = {name: value for name, value in given.items() if value is not None}
    if getattr(args, "no_title", False):
        chosen["title"] = None
    parameters = inspect.signature(render).parameters
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in parameters.values()):
        return chosen
    for name in chosen:
        if name not in parameters:
            option = "--no-title" if name == "title" else f"--{name}"
            raise CommandError(f"{option} does not apply to this picture")
    return chosen

"""What the subcommands share: errors and signals, one-line messages, progress, the mesh,
pictures and output files (torch and the library imported when called).

No input is ever overwritten: every output is compared with every input and the other
outputs before anything is computed, and written through
:func:`~stochlap_torch._common.files.atomic_write`.
"""

from __future__ import annotations

import argparse
import inspect
import logging
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from .._common.files import atomic_write, node_kind, same_file

PROG = "stochlap"
VIZ_HINT = 'pip install "stochlap_torch[viz]"'
#: The signals that end a command by :class:`Terminated` (SIGINT already raises
#: ``KeyboardInterrupt``); SIGHUP does not exist on Windows.
TERMINATING = tuple(getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n))


class CommandError(Exception):
    """A problem with the user's input, reported as one line and exit status 2."""


class Terminated(BaseException):
    """SIGTERM or SIGHUP received while a command ran (exit status ``128 + signum``); a
    ``BaseException`` like ``KeyboardInterrupt``: ``except Exception`` does not swallow it, and
    every cleanup on the way out runs (a file being written removes its temporary)."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)
        self.name = signal.Signals(self.signum).name


@contextmanager
def terminate_by_exception() -> Iterator[None]:
    """While the block runs, SIGTERM and SIGHUP raise :class:`Terminated` in the main thread:
    only signals at their default action (not one ``nohup`` ignores or an embedding program
    handles), put back on exit; a second signal while the first unwinds is ignored, so that
    cleanup is not cut short."""
    on_main = threading.current_thread() is threading.main_thread()
    taken = [s for s in TERMINATING if on_main and signal.getsignal(s) is signal.SIG_DFL]
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


class Parser(argparse.ArgumentParser):
    """Usage errors raise :class:`CommandError` (one line, by ``main``), not print and exit."""

    def error(self, message: str):
        raise CommandError(f"{message} (see '{self.prog} --help')")


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
    library before any work) as a :class:`CommandError`."""
    from .._common.errors import ParameterError

    try:
        yield
    except ParameterError as error:
        raise CommandError(str(error)) from None


def stderr_is_terminal() -> bool:
    try:
        return bool(sys.stderr.isatty())
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
    """``progress(k, K)`` callback: a ``scale k/K`` line on stderr, redrawn with ``\\r`` on a
    terminal, one line per scale otherwise; silent with ``quiet``."""

    def __init__(self, label: str, quiet: bool):
        self.label, self.quiet, self.start, self.width = label, quiet, time.perf_counter(), 0
        self.tty = stderr_is_terminal()

    def __call__(self, k: int, num_scales: int) -> None:
        if self.quiet:
            return
        elapsed = time.perf_counter() - self.start
        text = f"{self.label}: scale {k}/{num_scales} ({elapsed:.1f} s)"
        if self.tty:
            end = "\n" if k >= num_scales else ""
            self.width = max(self.width, len(text))
            sys.stderr.write(f"\r{text:<{self.width}}{end}")
        else:
            sys.stderr.write(f"{PROG}: {text}\n")
        sys.stderr.flush()


def apply_threads(requested: int) -> None:
    """Set torch's intra-op threads to ``requested``, capped at :func:`available_cpus` with a
    warning; the library's kernels follow ``torch.get_num_threads()``."""
    import torch

    from .._common.cpus import available_cpus

    cpus = available_cpus()
    if (count := min(requested, cpus)) < requested:
        warn(f"--threads {requested}: this process may use {cpus} CPUs, so {count} threads")
    torch.set_num_threads(count)


def mesh_path(given: str | None) -> Path:
    """The ``MESH`` argument, or the bundled cow."""
    if given is not None:
        return Path(given)
    from ..mesh import bundled_mesh_path

    return bundled_mesh_path("spot")


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
    import torch

    from ..mesh import load_mesh

    check_outputs([("mesh", path)], [*outputs, picture])
    draw = want_picture(args)
    mesh = load_mesh(path, merge_seams=args.merge_seams, dtype=getattr(torch, args.dtype))
    say(args, f"{path.name}: {mesh.num_vertices} vertices, {mesh.num_faces} faces")
    plys = [output for _, output in outputs if Path(output).suffix.lower() == ".ply"]
    if plys:  # refuse before computing what could not be written
        from ..mesh.io import check_ply_positions

        check_ply_positions(mesh.vertices.detach().cpu().numpy(), plys[0])
    return mesh, picture[1] if draw else None


def open_mesh_and_outputs(
    args, name: str, extension: str
) -> tuple[Path, object, Path, Path | None]:
    """:func:`open_mesh` of ``MESH`` for ``-o`` (default ``<stem>_<name>.<extension>``) and
    ``--png`` (default ``<stem>_<name>.png``); returns ``MESH``, the mesh and both paths."""
    path = mesh_path(args.mesh)
    out_path = Path(args.output or f"{path.stem}_{name}.{extension}")
    png_path = Path(args.png or f"{path.stem}_{name}.png")
    mesh, png_path = open_mesh(args, path, [("-o", out_path)], ("--png", png_path))
    return path, mesh, out_path, png_path


def draw_picture(args, path: Path | str | None, render: Callable, *arrays, **options) -> None:
    """Draw ``render(*arrays, path, **options)`` with ``--dpi``, ``--cmap``, ``--views``,
    ``--shading`` (those given) and ``--no-title`` (``title=None``), and say so; nothing when
    ``path`` is ``None``. An option ``render`` cannot use is refused, never ignored."""
    if path is None:
        return
    given = {name: getattr(args, name, None) for name in ("dpi", "cmap", "views", "shading")}
    chosen = {name: value for name, value in given.items() if value is not None}
    if getattr(args, "no_title", False):
        chosen["title"] = None
    parameters = inspect.signature(render).parameters
    for name in (name for name in chosen if name not in parameters):
        option = "--no-title" if name == "title" else f"--{name}"
        raise CommandError(f"{option} does not apply to this picture")
    render(*arrays, path, **{**options, **chosen})
    say(args, f"wrote {path}")


def check_outputs(
    inputs: Sequence[tuple[str, str | Path]], outputs: Sequence[tuple[str, str | Path | None]]
) -> None:
    """Refuse (:class:`CommandError`, naming the option and both files) ``(option, path)``
    outputs (``None``: not written) that would overwrite a ``(role, path)`` input, a directory
    or another node that is not a regular file (a FIFO, a device, a socket), or each other."""
    written = [(option, Path(path)) for option, path in outputs if path is not None]
    for index, (option, path) in enumerate(written):
        kind = node_kind(path)
        if kind == "a directory":
            raise CommandError(f"{option} {path} is a directory, not a file")
        if kind is not None:
            raise CommandError(
                f"{option} {path} is {kind}, not a regular file; refusing to replace it"
            )
        for role, source in inputs:
            if same_file(path, source):
                raise CommandError(
                    f"{option} {path} is the input {role} {source}; refusing to overwrite it"
                )
        for other_option, other in written[:index]:
            if same_file(path, other):
                raise CommandError(
                    f"{option} {path} and {other_option} {other} are the same file; give "
                    "different names"
                )


def write_text(path: str | Path, texts: Iterable[str]) -> None:
    """Write ``texts`` as a UTF-8 file, atomically; they may be produced while writing (a
    failure then names the file)."""
    try:
        with atomic_write(path, "wb") as handle:
            for text in texts:
                handle.write(text.encode("utf-8"))
    except OSError as exc:
        if exc.filename is None:  # a failed write names the file it was for
            exc.filename = str(path)
        raise


def describe_os_error(exc: OSError) -> str:
    """``<file>: <reason>`` for a failed file operation (both files for a rename)."""
    if exc.filename is None:
        return str(exc) or exc.strerror or type(exc).__name__
    names = exc.filename if exc.filename2 is None else f"{exc.filename} -> {exc.filename2}"
    return f"{names}: {exc.strerror or str(exc) or type(exc).__name__}"

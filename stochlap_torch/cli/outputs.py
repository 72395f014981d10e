"""Output files: their default names, the checks made before any work, and safe writing.

No input is ever overwritten: every output is compared with every input and the other
outputs before anything is computed (a FIFO, a device or a socket is refused then too), and
written through :func:`~stochlap_torch._common.files.atomic_write` (a failed write leaves the
earlier file, permissions and links are kept, a node that took the name meanwhile is refused).
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Sequence
from pathlib import Path

from .._common.files import atomic_write, node_kind, same_file
from .errors import CommandError


def default_output(given: str | None, mesh: Path, suffix: str, extension: str) -> Path:
    """``given``, or ``<mesh stem>_<suffix>.<extension>`` in the current directory."""
    return Path(given) if given else Path(f"{mesh.stem}_{suffix}.{extension}")


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


def write_lines(path: str | Path, lines: Iterable[str]) -> Path:
    """Write ``lines`` (each without its newline) as a UTF-8 text file, atomically."""
    return _write(path, (line + "\n" for line in lines))


def write_json(path: str | Path, data) -> Path:
    """Write ``data`` as indented JSON, atomically."""
    return _write(path, [json.dumps(data, indent=2) + "\n"])


def _write(path: str | Path, texts: Iterable[str]) -> Path:
    path = Path(path)
    try:
        with atomic_write(path, "wb") as handle:
            for text in texts:  # produced while writing: a failure names the file
                handle.write(text.encode("utf-8"))
    except OSError as exc:
        if exc.filename is None:  # a failed write names the file it was for
            exc.filename = str(path)
        raise
    return path


def describe_os_error(exc: OSError) -> str:
    """``<file>: <reason>`` for a failed file operation (both files for a rename)."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    if exc.filename is not None and exc.filename2 is not None:
        return f"{exc.filename} -> {exc.filename2}: {reason}"
    if exc.filename is not None:
        return f"{exc.filename}: {reason}"
    return str(exc) or reason

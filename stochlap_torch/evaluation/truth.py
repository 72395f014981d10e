"""Human-marked ground truth files: UTF-8 text, one line per subject holding the vertex
indices that subject marked, separated by spaces, tabs, commas or semicolons (0-based unless
the reader is told otherwise). Text after ``#`` is a comment and blank lines are skipped, so a
subject who marked nothing is written as ``-`` alone on its line.
"""

from __future__ import annotations

import re
from pathlib import Path

from .._common.errors import FileFormatError

_SEPARATORS = re.compile(r"[\s,;]+")


def read_marks(path: str | Path, num_vertices: int, one_based: bool = False) -> list[list[int]]:
    """Read a ground-truth file (format in the module docstring).

    Args:
        path: the text file.
        num_vertices: ``V`` of the mesh, to check the indices.
        one_based: the file counts vertices from 1.

    Returns:
        One list of 0-based vertex indices per subject (possibly empty).

    Raises:
        FileFormatError: not UTF-8 text, a token that is not an integer, an index out of
            range, or no marks at all.
        OSError: the file cannot be read.
    """
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError as exc:
        raise FileFormatError(
            f"{path}: not a text file of vertex indices (byte {exc.start} is not UTF-8)"
        ) from None
    subjects: list[list[int]] = []
    for number, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        marks = []  # "-": a subject who marked nothing
        for token in [] if line == "-" else filter(None, _SEPARATORS.split(line)):
            try:
                index = int(token)
            except ValueError:
                raise FileFormatError(
                    f"{path}:{number}: expected vertex indices, got {token!r}"
                ) from None
            index -= int(one_based)
            if not 0 <= index < num_vertices:
                base = "1-based" if one_based else "0-based"
                raise FileFormatError(
                    f"{path}:{number}: vertex {token} is out of range for a mesh of "
                    f"{num_vertices} vertices ({base} indices)"
                )
            marks.append(index)
        subjects.append(marks)
    if not any(subjects):
        raise FileFormatError(f"{path}: no marked vertices")
    return subjects

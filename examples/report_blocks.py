"""Shared by the example scripts: rewrite a marked block of a markdown report in place."""

from __future__ import annotations

from pathlib import Path


def write_block(path: Path, key: str, text: str) -> None:
    """Replace the text between ``<!-- BEGIN key -->`` and ``<!-- END key -->`` in ``path``
    (appending the block if it is missing)."""
    begin, end = f"<!-- BEGIN {key} -->", f"<!-- END {key} -->"
    block = f"{begin}\n{text}\n{end}"
    content = path.read_text() if path.exists() else ""
    if begin in content and end in content:
        head, rest = content.split(begin, 1)
        _, tail = rest.split(end, 1)
        content = head + block + tail
    else:
        content = content.rstrip("\n") + ("\n\n" if content else "") + block + "\n"
    path.write_text(content)

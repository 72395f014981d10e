"""Every Python block of the README and of the documentation runs.

Each fenced ```` ```python ```` block of ``README.md`` and ``docs/**/*.md`` is run on its own,
in a fresh namespace, with a temporary directory as the working directory, so a snippet can
never rot: an API change that breaks one fails here. A block may be left out only by starting
it with the marker comment ``# snippet: skip (why)``, the reason given; use it sparingly (a
snippet that needs a file the reader has and the test has not). Snippets are kept fast: they
run on the bundled mesh.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP = re.compile(r"^# snippet: skip \((?P<why>[^)]+)\)")
#: Generated or copied pages, not sources.
EXCLUDED = ("docs/_build", "docs/auto_examples")
FENCE = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}|~{3,})(?P<info>[^\n`]*)$")


def python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line, code)`` of every fenced block whose info string is ``python`` (1-based line of
    the block's first code line), indentation of the fence removed."""
    blocks, lines, index = [], text.splitlines(), 0
    while index < len(lines):
        opening = FENCE.match(lines[index])
        index += 1
        if opening is None:
            continue
        fence, indent = opening["fence"], len(opening["indent"])
        start, body = index, []
        while index < len(lines):
            closing = FENCE.match(lines[index])
            if closing and closing["fence"].startswith(fence) and not closing["info"].strip():
                break
            body.append(lines[index][indent:])
            index += 1
        index += 1
        if opening["info"].strip() == "python":
            blocks.append((start + 1, "\n".join(body) + "\n"))
    return blocks


def snippet_sources() -> list[Path]:
    pages = sorted((ROOT / "docs").rglob("*.md"))
    pages = [page for page in pages if not str(page.relative_to(ROOT)).startswith(EXCLUDED)]
    return [ROOT / "README.md", *pages]


def collect() -> list:
    cases = []
    for path in snippet_sources():
        name = path.relative_to(ROOT).as_posix()
        for line, code in python_blocks(path.read_text(encoding="utf-8")):
            skip = SKIP.match(code)
            marks = [pytest.mark.skip(reason=skip["why"])] if skip else []
            cases.append(pytest.param(name, line, code, id=f"{name}:{line}", marks=marks))
    return cases


@pytest.mark.parametrize(("name", "line", "code"), collect())
def test_snippet_runs(name, line, code, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # line numbers of a traceback are those of the page
    compiled = compile("\n" * (line - 1) + code, str(ROOT / name), "exec")
    exec(compiled, {"__name__": "__snippet__"})


def test_blocks_are_found_and_fenced_text_is_not():
    page = "\n".join(
        [
            "text",
            "```python",
            "a = 1",
            "```",
            "````markdown",
            "```python",
            "inside a longer fence: an example of markdown, not a snippet",
            "```",
            "````",
            "- item:",
            "  ```python",
            "  b = 2",
            "  ```",
            "```bash",
            "echo no",
            "```",
        ]
    )
    assert python_blocks(page) == [(3, "a = 1\n"), (12, "b = 2\n")]


def test_every_page_is_searched_and_the_skip_marker_needs_a_reason():
    sources = {path.relative_to(ROOT).as_posix() for path in snippet_sources()}
    assert {"README.md", "docs/quickstart.md", "docs/guide/training.md"} <= sources
    assert SKIP.match("# snippet: skip (needs the reader's own bunny.obj)\nx = 1\n")
    assert not SKIP.match("# snippet: skip\nx = 1\n")
    assert not SKIP.match("x = 1  # snippet: skip (not on the first line)\n")

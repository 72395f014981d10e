"""Every Python block of the README and of the documentation runs.

Each fenced ```` ```python ```` block of ``README.md`` and ``docs/**/*.md``, and each
``.. code-block:: python`` directive of ``docs/**/*.rst`` (the API reference, where every public
name has an example), is run on its own, in a fresh namespace, with a temporary directory as the
working directory, so a snippet can never rot: an API change that breaks one fails here. A block
may be left out only by starting it with the marker comment ``# snippet: skip (why)``, the reason
given; use it sparingly (a snippet that needs a file the reader has and the test has not).
Snippets are kept fast: they run on the bundled mesh or on a small sphere.
"""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP = re.compile(r"^# snippet: skip \((?P<why>[^)]+)\)")
#: Generated or copied pages, not sources.
EXCLUDED = ("docs/_build", "docs/auto_examples")
FENCE = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}|~{3,})(?P<info>[^\n`]*)$")
CODE_BLOCK = re.compile(r"^(?P<indent> *)\.\. (?:code-block|code|sourcecode):: *python *$")


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


def _inside(line: str, indent: int) -> bool:
    """Whether ``line`` belongs to the content of a directive indented by ``indent``."""
    return not line.strip() or len(line) - len(line.lstrip(" ")) > indent


def rst_python_blocks(text: str) -> list[tuple[int, str]]:
    """``(line, code)`` of every ``.. code-block:: python`` directive of a reStructuredText page
    (1-based line of the block's first code line), its options skipped and its content dedented;
    the content ends at the first non-blank line indented no deeper than the directive."""
    blocks, lines, index = [], text.splitlines(), 0
    while index < len(lines):
        opening = CODE_BLOCK.match(lines[index])
        index += 1
        if opening is None:
            continue
        indent = len(opening["indent"])
        while (
            index < len(lines)
            and _inside(lines[index], indent)
            and lines[index].strip().startswith(":")
        ):
            index += 1  # the directive's options (:caption:, :emphasize-lines:)
        while index < len(lines) and not lines[index].strip():
            index += 1
        start, body = index, []
        while index < len(lines) and _inside(lines[index], indent):
            body.append(lines[index])
            index += 1
        while body and not body[-1].strip():
            body.pop()
        if body:
            depth = min(len(line) - len(line.lstrip(" ")) for line in body if line.strip())
            blocks.append((start + 1, "\n".join(line[depth:] for line in body) + "\n"))
    return blocks


def snippet_sources() -> list[Path]:
    pages = sorted((ROOT / "docs").rglob("*.md")) + sorted((ROOT / "docs").rglob("*.rst"))
    pages = [page for page in pages if not str(page.relative_to(ROOT)).startswith(EXCLUDED)]
    return [ROOT / "README.md", *pages]


def page_blocks(path: Path) -> list[tuple[int, str]]:
    """The Python blocks of a page, by its format."""
    text = path.read_text(encoding="utf-8")
    return rst_python_blocks(text) if path.suffix == ".rst" else python_blocks(text)


def collect() -> list:
    cases = []
    for path in snippet_sources():
        name = path.relative_to(ROOT).as_posix()
        for line, code in page_blocks(path):
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
    assert {
        "README.md",
        "docs/quickstart.md",
        "docs/guide/training.md",
        "docs/api/index.rst",
    } <= sources
    assert SKIP.match("# snippet: skip (needs the reader's own bunny.obj)\nx = 1\n")
    assert not SKIP.match("# snippet: skip\nx = 1\n")
    assert not SKIP.match("x = 1  # snippet: skip (not on the first line)\n")


def test_rst_code_blocks_are_found_with_their_page_lines():
    page = "\n".join(
        [
            ".. autofunction:: f",
            "",
            "   .. code-block:: python",
            "      :caption: an option",
            "",
            "      a = 1",
            "",
            "      if a:",
            "          b = 2",
            "",
            "   Text after the block.",
            "",
            ".. code-block:: bash",
            "",
            "   echo no",
            "",
            ".. code-block:: python",
            "",
            "   c = 3",
        ]
    )
    assert rst_python_blocks(page) == [(6, "a = 1\n\nif a:\n    b = 2\n"), (19, "c = 3\n")]


# -- the API reference: an example of every public name ---------------------------------------

API = ROOT / "docs" / "api"


def api_module(page: Path) -> str:
    """The module whose ``__all__`` an API page documents."""
    return "stochlap_torch" if page.stem == "index" else f"stochlap_torch.{page.stem}"


def names_shown(code: str) -> set[str]:
    """The names a block uses as a module's or an object's attribute (``sl.load_mesh``,
    ``mesh.vertices``) or imports by name (``from stochlap_torch.mesh import face_areas``)."""
    shown = set()
    for node in ast.walk(ast.parse(code)):
        if isinstance(node, ast.Attribute):
            shown.add(node.attr)
        elif isinstance(node, ast.ImportFrom):
            shown.update(alias.name for alias in node.names)
    return shown


def missing_examples(page: Path) -> list[str]:
    """The public names of the page's module that no executed block of the page uses."""
    shown = set()
    for _, code in page_blocks(page):
        if not SKIP.match(code):
            shown |= names_shown(code)
    module = importlib.import_module(api_module(page))
    return [name for name in module.__all__ if not name.startswith("__") and name not in shown]


def test_every_subpackage_of_the_reference_has_its_page():
    index = (API / "index.rst").read_text(encoding="utf-8")
    listed = re.findall(r"^   (\w+)$", index.split(".. toctree::", 1)[1], flags=re.MULTILINE)
    pages = sorted(page.stem for page in API.glob("*.rst") if page.stem != "index")
    assert sorted(listed) == pages
    for page in pages:
        assert importlib.import_module(f"stochlap_torch.{page}").__all__


@pytest.mark.parametrize("page", sorted(API.glob("*.rst")), ids=lambda page: page.name)
def test_every_public_name_has_an_example(page):
    missing = missing_examples(page)
    assert not missing, (
        f"docs/api/{page.name}: no executed example uses {', '.join(missing)}; add a "
        "`.. code-block:: python` example after its entry"
    )


def test_an_example_counts_only_where_it_runs():
    assert names_shown("import stochlap_torch as sl\nm = sl.load_mesh(p)\n") >= {"load_mesh"}
    assert "face_areas" in names_shown("from stochlap_torch.mesh import face_areas\n")
    assert "load_mesh" not in names_shown("# sl.load_mesh in a comment\nx = 'load_mesh'\n")

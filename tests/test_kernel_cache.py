"""The compiled-kernel disk cache follows every source a kernel is compiled from.

numba stamps a cached kernel with its own file only, while ``rows._packed_first_rows`` inlines
``block._first_row``: after an edit of ``block.py`` the cache must not serve the old machine
code. Each run is a fresh interpreter on a copy of the package, with a private cache.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from stochlap_torch._kernels import jit, numba_available

PACKAGE = Path(__file__).resolve().parents[1] / "stochlap_torch"

pytestmark = pytest.mark.skipif(not numba_available(), reason="numba is not installed")

# Rows of F^(1) = Lhat normalised by its row sums, for a 2 x 2 Lhat with diagonal (1, 2), off
# diagonal (3, 4) and row sums (4, 6); prints the values and whether the kernel was compiled.
SCRIPT = """
    import json
    import numpy as np
    from stochlap_torch._kernels import block, jit, rows

    lhat = block.SplitLhat(
        diagonal=np.array([1.0, 2.0]), w_crow=np.array([0, 1, 2]), w_col=np.array([1, 0]),
        w_val=np.array([3.0, 4.0]), row_sums=np.array([4.0, 6.0]),
    )
    kernel = rows._packed_first_rows
    _, values = kernel(lhat, np.arange(2), np.empty(4, dtype=np.int64))
    print(json.dumps({
        "values": values.tolist(),
        "hits": sum(kernel.stats.cache_hits.values()),
        "misses": sum(kernel.stats.cache_misses.values()),
        "cache": jit.cache_directory(kernel),
    }))
"""

# The one line of block._first_row that the edit changes: every F^(1) entry halves.
HELPER_LINE = "        scale = lhat.row_sums[row]\n"
EDITED_LINE = "        scale = 2.0 * lhat.row_sums[row]\n"


def _run(root: Path, env: dict[str, str]) -> dict:
    result = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(SCRIPT)],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=root,
        env=env,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    return json.loads(result.stdout.splitlines()[-1])


@pytest.fixture
def package_copy(tmp_path) -> Path:
    """A copy of the package whose ``_kernels/__pycache__`` is a regular file, so that numba's
    in-tree cache cannot be used and the kernels cache under ``$STOCHLAP_CACHE_DIR``."""
    root = tmp_path / "install"
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(PACKAGE, root / "stochlap_torch", ignore=ignore)
    (root / "stochlap_torch" / "_kernels" / "__pycache__").write_text("")
    return root


def test_editing_an_inlined_helper_recompiles_the_kernel(package_copy, tmp_path):
    blocked = tmp_path / "a_file"  # nothing can be created under a regular file
    blocked.write_text("")
    cache_dir = tmp_path / "kernel-cache"
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(
        PYTHONPATH=str(package_copy),
        STOCHLAP_CACHE_DIR=str(cache_dir),
        XDG_CACHE_HOME=str(blocked / "xdg"),
        HOME=str(blocked / "home"),
        PYTHONDONTWRITEBYTECODE="1",
        STOCHLAP_QUIET="1",
    )

    first = _run(package_copy, env)
    assert first["values"] == [1 / 4, 3 / 4, 4 / 6, 2 / 6]
    assert first["misses"] == 1 and first["hits"] == 0
    assert Path(first["cache"]).is_relative_to(cache_dir)
    again = _run(package_copy, env)  # unchanged sources: served from the disk cache
    assert (again["values"], again["misses"], again["hits"]) == (first["values"], 0, 1)

    helper = package_copy / "stochlap_torch" / "_kernels" / "block.py"
    source = helper.read_text()
    assert source.count(HELPER_LINE) == 1
    helper.write_text(source.replace(HELPER_LINE, EDITED_LINE))

    edited = _run(package_copy, env)
    assert edited["values"] == [v / 2 for v in first["values"]]
    assert edited["misses"] == 1 and edited["hits"] == 0
    cached = _run(package_copy, env)  # the recompiled kernel replaced the stale entry
    assert (cached["values"], cached["misses"], cached["hits"]) == (edited["values"], 0, 1)


def test_sources_digest_follows_every_file_of_its_folders(tmp_path):
    folder = tmp_path / "kernels"
    folder.mkdir()
    (folder / "a.py").write_text("x = 1\n")
    (folder / "b.py").write_text("y = 2\n")
    (folder / "notes.txt").write_text("not a source")
    digests = [jit.sources_digest.__wrapped__((str(folder),))]
    (folder / "notes.txt").write_text("still not a source")
    assert jit.sources_digest.__wrapped__((str(folder),)) == digests[0]
    (folder / "b.py").write_text("y = 3\n")
    digests.append(jit.sources_digest.__wrapped__((str(folder),)))
    (folder / "c.py").write_text("")
    digests.append(jit.sources_digest.__wrapped__((str(folder),)))
    assert len(set(digests)) == 3


def _kernel_modules() -> list:
    """Every module of the package that defines a cached kernel (uses ``kernel_jit``)."""
    names = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if "kernel_jit(" in path.read_text() and path.name != "jit.py":
            parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
            names.append(".".join(parts))
    return [importlib.import_module(name) for name in names]


def _compiled_helpers(function) -> set:
    """The numba functions ``function`` calls through its globals or closure (one level)."""
    found = set()
    codes = [function.__code__]
    while codes:
        code = codes.pop()
        codes.extend(c for c in code.co_consts if inspect.iscode(c))
        for name in code.co_names:
            value = function.__globals__.get(name)
            if hasattr(value, "py_func") or hasattr(value, "_defn"):
                found.add(value)
    for cell in function.__closure__ or ():
        if hasattr(cell.cell_contents, "py_func"):
            found.add(cell.cell_contents)
    return found


def test_every_helper_a_kernel_compiles_is_in_its_stamp():
    """The stamp covers the kernel's folder and ``_kernels``: every numba helper a cached
    kernel reaches, however deep, is defined there (else editing it would not recompile)."""
    kernels = [
        value
        for module in _kernel_modules()
        for value in vars(module).values()
        if isinstance(getattr(value, "_cache", None), jit._CACHE_CLASS)
    ]
    assert len(kernels) >= 10
    crossings = 0
    for kernel in kernels:
        folders = jit.kernel_source_folders(inspect.getfile(kernel.py_func))
        kernel_file = inspect.getfile(kernel.py_func)
        seen, todo = set(), [kernel]
        while todo:
            helper = todo.pop()
            function = getattr(helper, "py_func", None) or helper._defn
            source = inspect.getfile(function)
            assert os.path.dirname(os.path.abspath(source)) in folders, (kernel, helper)
            crossings += source != kernel_file
            for reached in _compiled_helpers(function) - seen:
                seen.add(reached)
                todo.append(reached)
    assert crossings > 0  # rows._packed_first_rows reaches block._first_row, at least

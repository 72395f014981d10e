"""Issue 23 §2: the compiled-kernel disk cache follows every source a kernel is compiled from.

numba stamps a cached kernel with its own file only, while ``rows._packed_first_rows`` inlines
``block._first_row``: after an edit of ``block.py`` the cache must not serve the old machine
code. Each run is a fresh interpreter on a copy of the package, with a private cache.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from stochlap_torch._kernels import numba_available

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


def test_issue23_editing_an_inlined_helper_recompiles_the_kernel(package_copy, tmp_path):
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

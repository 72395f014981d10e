"""Where the compiled kernels cache: a writable fallback directory when the install is
read-only, else no cache and a ``KernelCacheWarning``; importing and calling the library never
fails. Each case runs a fresh interpreter with exactly the environment it sets.

Root ignores permission bits, so an unwritable path here is one under a regular file:
``makedirs`` fails for anyone.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
PACKAGE = TESTS.parent / "stochlap_torch"


def _python(script: str, env: dict[str, str], timeout: float = 300) -> subprocess.CompletedProcess:
    """Run ``script`` in a fresh interpreter from tests/ with exactly ``env``."""
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(script)],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=TESTS,
        env=env,
        check=False,
    )


CACHE_SCRIPT = """
    import os, tempfile, warnings
    if os.environ.get("TEST_TEMPDIR"):  # what TMPDIR cannot do alone: tempfile falls back
        tempfile.tempdir = os.environ["TEST_TEMPDIR"]  # to /tmp, which root can write
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        import stochlap_torch
        from stochlap_torch._kernels import buffers, jit  # the kernels find their cache here
        finite = None
        if CALL:
            import torch, trimesh
            sphere = trimesh.creation.icosphere(1)
            vertices = torch.tensor(sphere.vertices) * torch.tensor([1.0, 1.2, 0.9])
            values = stochlap_torch.saliency(vertices, torch.tensor(sphere.faces))
            finite = bool(torch.isfinite(values).all())
    print(stochlap_torch.__file__)
    print(jit.cache_directory(buffers._fill_worker))
    print(finite)
    print(sorted({w.category.__name__ for w in caught if "Cache" in w.category.__name__}))
"""


def _cache_env(blocked: Path, **overrides: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "NUMBA_CACHE_DIR"}
    env.update(
        STOCHLAP_CACHE_DIR=str(blocked / "stochlap"),
        XDG_CACHE_HOME=str(blocked / "xdg"),
        TMPDIR=str(blocked / "tmp"),
        HOME=str(blocked / "home"),
        PYTHONDONTWRITEBYTECODE="1",
        STOCHLAP_QUIET="1",
    )
    env.update(overrides)
    return env


@pytest.fixture(scope="module")
def blocked(tmp_path_factory) -> Path:
    """A regular file: no directory can be created under it."""
    path = tmp_path_factory.mktemp("cache") / "a_file"
    path.write_text("")
    return path


@pytest.fixture(scope="module")
def readonly_install(tmp_path_factory) -> Path:
    """A copy of the package whose every ``__pycache__`` is a regular file: numba's in-tree
    cache locator cannot be used, as in a read-only install. Returns the folder to put on
    ``PYTHONPATH``."""
    root = tmp_path_factory.mktemp("install")
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
    shutil.copytree(PACKAGE, root / "stochlap_torch", ignore=ignore)
    for folder in [root / "stochlap_torch", *(root / "stochlap_torch").rglob("*")]:
        if folder.is_dir():
            (folder / "__pycache__").write_text("")
    return root


def test_library_works_with_no_writable_cache_directory_in_env(blocked):
    """The package of this checkout (numba caches beside its sources first, as in an editable
    install) imports and computes with every cache variable pointing nowhere."""
    env = _cache_env(blocked, PYTHONPATH=str(PACKAGE.parent))
    result = _python("CALL = True\n" + textwrap.dedent(CACHE_SCRIPT), env)
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.splitlines()
    assert lines[0] == str(PACKAGE / "__init__.py")
    assert lines[2] == "True"


@pytest.mark.parametrize("fallback", ["STOCHLAP_CACHE_DIR", "TMPDIR"])
def test_readonly_install_caches_in_the_first_writable_fallback(
    blocked, readonly_install, tmp_path, fallback
):
    writable = tmp_path / "writable"
    if fallback == "TMPDIR":
        writable.mkdir()  # tempfile skips a TMPDIR that does not exist
    env = _cache_env(blocked, PYTHONPATH=str(readonly_install), **{fallback: str(writable)})
    result = _python("CALL = False\n" + textwrap.dedent(CACHE_SCRIPT), env)
    assert result.returncode == 0, result.stderr[-3000:]
    package, directory, finite, warned = result.stdout.splitlines()
    assert package == str(readonly_install / "stochlap_torch" / "__init__.py")
    expected = writable
    if fallback == "TMPDIR":
        expected = writable / f"stochlap_torch-{os.getuid()}"
    assert Path(directory).is_relative_to(expected / "numba"), directory
    assert Path(directory).is_dir()
    assert (finite, warned) == ("None", "[]")
    if fallback == "TMPDIR":  # a shared temporary directory: private to the user
        assert expected.stat().st_mode & 0o777 == 0o700


def test_readonly_install_without_any_cache_warns_and_computes(blocked, readonly_install):
    env = _cache_env(blocked, PYTHONPATH=str(readonly_install), TEST_TEMPDIR=str(blocked))
    result = _python("CALL = True\n" + textwrap.dedent(CACHE_SCRIPT), env)
    assert result.returncode == 0, result.stderr[-3000:]
    package, directory, finite, warned = result.stdout.splitlines()
    assert package == str(readonly_install / "stochlap_torch" / "__init__.py")
    assert directory == "None"  # compiled uncached
    assert finite == "True"
    assert warned == "['KernelCacheWarning']"

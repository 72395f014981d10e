"""Shared fixtures: the small synthetic meshes of ``reference.py`` and the real-mesh folder."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

TESTS_DIR = Path(__file__).resolve().parent
REPO_ROOT = TESTS_DIR.parent
MESHES_DIR = REPO_ROOT.parent / "shared" / "meshes"

# The test modules import ``reference`` (this folder), and the suite also runs from a plain
# checkout where the package is not installed; both work whatever pytest's import mode is.
for folder in (TESTS_DIR, REPO_ROOT):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))

from reference import SMALL_MESH_BUILDERS, SmallMesh, noisy_sphere  # noqa: E402


@pytest.fixture(params=sorted(SMALL_MESH_BUILDERS))
def small_mesh(request) -> SmallMesh:
    """Every small synthetic mesh in turn."""
    return SMALL_MESH_BUILDERS[request.param]()


@pytest.fixture
def bumpy() -> SmallMesh:
    """The radially jittered icosphere(2), 162 vertices, no symmetric ties."""
    return noisy_sphere()


@pytest.fixture(scope="session")
def meshes_dir() -> Path:
    """The shared real-mesh folder; skips when it is not next to the repository."""
    if not MESHES_DIR.is_dir():
        pytest.skip(f"real meshes not found at {MESHES_DIR} (expected ../shared/meshes)")
    return MESHES_DIR

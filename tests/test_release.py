"""Release hygiene: licence, typing marker, changelog and ignored outputs."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import tomllib

import stochlap_torch

ROOT = Path(__file__).resolve().parents[1]


def test_license_file_matches_the_declared_licence():
    declared = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["license"]
    assert declared == {"text": "MIT"}
    assert (ROOT / "LICENSE").read_text().startswith("MIT License")


def test_package_ships_py_typed():
    package = Path(stochlap_torch.__file__).parent
    assert (package / "py.typed").is_file()
    data = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert "py.typed" in data["package-data"]["stochlap_torch"]


def test_changelog_describes_the_current_version():
    changelog = (ROOT / "CHANGELOG.md").read_text()
    assert f"## {stochlap_torch.__version__}" in changelog


@pytest.mark.skipif(
    shutil.which("git") is None or not (ROOT / ".git").exists(), reason="needs a git checkout"
)
@pytest.mark.parametrize(
    "output",
    [
        "spot_saliency.ply",
        "spot_saliency.png",
        "out/spot_k3.ply",
        "spot_interest.txt",
        "benchmarks/.cache/horse_acvd.npz",
    ],
)
def test_outputs_of_the_readme_commands_are_ignored(output):
    result = subprocess.run(["git", "check-ignore", "-q", output], cwd=ROOT, check=False)
    assert result.returncode == 0, f"{output} is not git-ignored"

"""``stochlap --help`` and ``stochlap <command> --help`` load neither torch nor the library."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGE = REPO_ROOT / "stochlap_torch"
COMMANDS = ("saliency", "multiscale", "interest", "info", "evaluate", "features")
#: Top-level modules a help screen must not import (torch alone takes seconds).
HEAVY = ("torch", "numpy", "scipy", "numba", "matplotlib", "trimesh")
#: The parts of the package a help screen may import (``evaluate --help`` lists the method
#: names of the torch-free ``evaluation.constants``; the evaluation package imports lazily).
ALLOWED = (
    "stochlap_torch",
    "stochlap_torch.__main__",
    "stochlap_torch.evaluation",
    "stochlap_torch.evaluation.constants",
    "stochlap_torch.params",  # the methods' defaults, for the help text; imports no torch
)
ALLOWED_PACKAGES = ("stochlap_torch.cli", "stochlap_torch._common")


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO_ROOT), env.get("PYTHONPATH")]))
    return env


def _allowed(name: str) -> bool:
    if name.split(".")[0] in HEAVY:
        return False
    if name.split(".")[0] != "stochlap_torch" or name in ALLOWED:
        return True
    return any(name == p or name.startswith(p + ".") for p in ALLOWED_PACKAGES)


def _unwanted(modules) -> list[str]:
    """The modules of ``modules`` a help screen should not have imported, in import order."""
    return [name for name in modules if not _allowed(name)]


# A script that runs the CLI's help screens with the package's own __init__ replaced by an
# empty package: what the cli package imports by itself, whatever the top-level __init__ does.
CLI_ONLY = f"""
import sys, types
package = types.ModuleType("stochlap_torch")
package.__path__ = [{str(PACKAGE)!r}]
sys.modules["stochlap_torch"] = package
from stochlap_torch.cli import main
for argv in [["--help"]] + [[command, "--help"] for command in {COMMANDS!r}]:
    assert main(argv) == 0, argv
print("\\n".join(sorted(sys.modules)))
"""


def test_cli_package_imports_nothing_heavy_for_help():
    result = subprocess.run(
        [sys.executable, "-c", CLI_ONLY],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert result.returncode == 0, result.stderr
    modules = [line for line in result.stdout.splitlines() if "." in line or line.isidentifier()]
    assert _unwanted(modules) == []


def _importtime(argv: list[str]) -> tuple[float, list[str], subprocess.CompletedProcess]:
    start = time.perf_counter()
    result = subprocess.run(
        [sys.executable, "-X", "importtime", "-m", "stochlap_torch", *argv],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    elapsed = time.perf_counter() - start
    # -X importtime: "import time: <self us> | <cumulative us> | <indented module name>"
    modules = [
        line.rsplit("|", 1)[1].strip()
        for line in result.stderr.splitlines()
        if line.startswith("import time:") and line.count("|") == 2
    ]
    return elapsed, modules[1:], result  # the first line is the header


@pytest.mark.parametrize("argv", [["--help"], ["saliency", "--help"], ["evaluate", "--help"]])
def test_help_is_fast_and_does_not_import_torch(argv):
    elapsed, modules, result = _importtime(argv)
    assert result.returncode == 0, result.stderr
    assert "usage: stochlap" in result.stdout
    unwanted = _unwanted(modules)
    # -X importtime lists a module when its import completes: what completes before the
    # package itself was imported by its top-level __init__, not by the cli. Either way it is
    # a failure: the top-level names are loaded lazily (PEP 562), and must stay so.
    eager = bool(unwanted) and modules.index(unwanted[0]) < modules.index("stochlap_torch")
    where = "stochlap_torch/__init__.py (eagerly)" if eager else "the cli"
    assert unwanted == [], f"imported by {where}: {', '.join(unwanted[:5])}"
    assert elapsed < 2.0, f"{elapsed:.2f} s"

"""The package's structure: no import cycle, modules of a readable size, one loop over scales.

The layering itself (which subpackage may import which) is the import-linter contract in
``pyproject.toml``, checked by ``lint-imports`` in the README's test command; here it is run
once more so that a plain ``pytest`` catches a broken layer too.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).parents[1] / "stochlap_torch"
#: A module longer than this likely holds more than one concern (the size follows the concern:
#: split by concern, never by squeezing lines).
MAX_LINES = 600
#: The only places that loop over the scales: the one loop of the engine and the compiled
#: kernel that streams rows through every step.
SCALE_LOOPS = {"diffusion/step.py", "_kernels/steps.py", "_kernels/cuda_kernel.py"}


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def test_no_import_cycles() -> None:
    """No module imports, directly or through others, a module that imports it back (the
    package root, which only re-exports, excluded)."""
    grimp = pytest.importorskip("grimp")
    graph = grimp.build_graph("stochlap_torch")
    modules = sorted(m for m in graph.modules if m != "stochlap_torch")
    cycles = []
    for module in modules:
        for imported in graph.find_modules_directly_imported_by(module):
            if imported == "stochlap_torch" or imported not in modules:
                continue
            if graph.chain_exists(importer=imported, imported=module):
                cycles.append((module, imported))
    assert not cycles, f"import cycles: {cycles}"


def test_layers_contract_holds() -> None:
    lint = shutil.which("lint-imports") or shutil.which(
        "lint-imports", path=str(Path(sys.executable).parent)
    )
    if lint is None:
        pytest.skip("import-linter is not installed (pip install -e '.[test]')")
    result = subprocess.run([lint], capture_output=True, text=True, cwd=PACKAGE.parent)
    assert result.returncode == 0, result.stdout[-3000:]


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_module_size(path: Path) -> None:
    lines = len(path.read_text(encoding="utf-8").splitlines())
    assert lines <= MAX_LINES, f"{path.name} has {lines} lines"


def _loops_over_scales(tree: ast.AST) -> list[int]:
    """Line numbers of ``for`` loops over ``range(start, ...)`` calls that mention
    ``num_scales``: Algorithm 1's loop shape (``range(2, num_scales + 1)``); a plain
    ``range(num_scales)`` over results already computed is not one."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.For) and isinstance(node.iter, ast.Call):
            call = node.iter
            if getattr(call.func, "id", None) == "range" and len(call.args) >= 2:
                names = {
                    n.id for arg in call.args for n in ast.walk(arg) if isinstance(n, ast.Name)
                }
                if "num_scales" in names:
                    found.append(node.lineno)
    return found


def test_one_loop_over_scales() -> None:
    """Algorithm 1's loop over the scales is written once (plus the compiled kernel the engine
    drives); every other path calls the engine."""
    offenders = {}
    for path in _modules():
        relative = str(path.relative_to(PACKAGE))
        if relative in SCALE_LOOPS:
            continue
        lines = _loops_over_scales(ast.parse(path.read_text(encoding="utf-8")))
        if lines:
            offenders[relative] = lines
    assert not offenders, f"loops over the scales outside the engine: {offenders}"


def test_public_names_resolve_lazily() -> None:
    """The package root imports nothing heavy until a name is used, and every name of
    ``__all__`` resolves to the object its subpackage defines."""
    result = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, stochlap_torch as sl; assert 'torch' not in sys.modules; "
            "assert set(sl.__all__) == set(sl._EXPORTS) | {'__version__'}; "
            "[getattr(sl, name) for name in sl.__all__]; "
            "from stochlap_torch.saliency_maps import mesh_saliency; "
            "assert sl.saliency is mesh_saliency",
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stderr[-2000:]


def test_no_submodule_shadows_a_public_name() -> None:
    """Importing a submodule sets it as an attribute of its package: a module named like a
    public name (``stochlap_torch/warmup.py`` and ``sl.warmup()``) would turn the function
    into the module once anything imported it. After importing every module, each name of
    ``__all__`` is still what its home module defines."""
    code = (
        "import importlib, pkgutil, types, stochlap_torch as sl; "
        "expected = {name: getattr(sl, name) for name in sl._EXPORTS}; "
        "[importlib.import_module(m.name) for m in pkgutil.walk_packages(sl.__path__, "
        "'stochlap_torch.') if not m.name.endswith('__main__')]; "
        "bad = [n for n in sl._EXPORTS if getattr(sl, n) is not expected[n] "
        "or isinstance(getattr(sl, n), types.ModuleType)]; "
        "assert not bad, bad"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


#: How many of the package's modules a call of ``sl.saliency(v, f)`` may enter: a reader
#: follows the robust saliency through these, no more (issue 30: 24 before the redesign).
SALIENCY_MODULES = 14


def test_a_saliency_call_enters_few_modules() -> None:
    """``sl.saliency(v, f)`` on the bundled mesh, traced with ``sys.setprofile`` after a first
    call (imports and compilation done): the package modules whose functions it calls."""
    script = (
        "import sys, stochlap_torch as sl\n"
        "mesh = sl.load_mesh(sl.bundled_mesh_path())\n"
        "sl.saliency(mesh.vertices, mesh.faces)\n"
        "entered = set()\n"
        "def profile(frame, event, arg):\n"
        "    name = frame.f_globals.get('__name__', '')\n"
        "    if event == 'call' and name.startswith('stochlap_torch'):\n"
        "        entered.add(name)\n"
        "sys.setprofile(profile)\n"
        "sl.saliency(mesh.vertices, mesh.faces)\n"
        "sys.setprofile(None)\n"
        "print(' '.join(sorted(entered)))\n"
    )
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]
    entered = result.stdout.split()
    assert len(entered) <= SALIENCY_MODULES, entered


def test_the_paper_features_options_are_declared_once() -> None:
    """``include``, ``rotation_invariant`` and ``normalisation`` are fields of
    ``PaperFeatureParams``; no function of the package lists them again (entry points take
    them through ``**options``), so adding an option touches the dataclass alone."""
    options = {"include", "rotation_invariant", "normalisation"}
    listed = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                arguments = node.args.args + node.args.kwonlyargs + node.args.posonlyargs
                if options & {argument.arg for argument in arguments}:
                    listed.append(f"{path.relative_to(PACKAGE)}:{node.name}")
    assert listed == []

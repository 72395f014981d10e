"""Mutation check: plant one plausible bug at a time and make sure the test suite fails.

    python benchmarks/mutation_check.py            # every mutation
    python benchmarks/mutation_check.py --list     # their names
    python benchmarks/mutation_check.py -k cache   # those whose name contains "cache"

Each mutation replaces one exact piece of source in a scratch copy of the repository (never in
the working tree), then runs first the test files named as its likely catchers and, if they
all pass, the whole default suite. A mutation the suite passes is a hole in the tests: the
script lists each mutation with the first test that caught it, and exits 1 if any survived
(also if a run timed out: a hang is no catch; 2 if a mutation no longer applies because the
code it targets changed: update the list).

Keep :data:`MUTATIONS` growing: when a bug slips through review, add the mutation that plants
it and the test that catches it.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    """One planted bug: ``old`` (which must occur exactly once in ``path``) becomes ``new``.

    Attributes:
        name: short identifier.
        path: file, relative to the repository root.
        old: exact source text to replace.
        new: its mutated form.
        tests: test files (or node ids) expected to catch it, run first.
    """

    name: str
    path: str
    old: str
    new: str
    tests: tuple[str, ...] = ()


MUTATIONS = [
    Mutation(
        "robust-saliency-weighted-by-counts",
        "stochlap_torch/robust/channels.py",
        "    mean = _per_mesh_mean(dn, rep.mass, batch, num_meshes)",
        "    mean = _per_mesh_mean(dn, rep.referenced.to(dn.dtype), batch, num_meshes)",
        ("tests/test_robust_reference.py",),
    ),
    Mutation(
        "robust-saliency-deviation-weighted-by-counts",
        "stochlap_torch/robust/channels.py",
        "    variance = _per_mesh_mean(centred.square(), rep.mass, batch, num_meshes)",
        "    variance = _per_mesh_mean(centred.square(), rep.referenced.to(dn.dtype), batch,"
        " num_meshes)",
        ("tests/test_robust_reference.py",),
    ),
    Mutation(
        "robust-saliency-statistics-over-the-whole-batch",
        "stochlap_torch/robust/channels.py",
        "    num_meshes = int(batch.max()) + 1 if batch.numel() else 1",
        "    num_meshes = 1\n    batch = torch.zeros_like(batch)",
        ("tests/test_robust_reference.py",),
    ),
    Mutation(
        "robust-saliency-absolute-instead-of-positive-part",
        "stochlap_torch/robust/channels.py",
        "    saliency = standard.clamp_min(0.0).mean(dim=1)",
        "    saliency = standard.abs().mean(dim=1)",
        ("tests/test_robust_reference.py",),
    ),
    Mutation(
        "interest-nms-extent-over-all-vertices",
        "stochlap_torch/interest.py",
        "    extent = points[on_surface].max(axis=0) - points[on_surface].min(axis=0)",
        "    extent = points.max(axis=0) - points.min(axis=0)",
        ("tests/test_robust_reference.py", "tests/test_interest.py"),
    ),
    Mutation(
        "interest-candidates-range-over-all-vertices",
        "stochlap_torch/interest.py",
        "    low, high = saliency[on_surface].min(), saliency[on_surface].max()",
        "    low, high = saliency.min(), saliency.max()",
        ("tests/test_robust_reference.py", "tests/test_interest.py"),
    ),
    Mutation(
        "cache-key-ignores-settings-fields",
        "stochlap_torch/learning/cache.py",
        "        return {type(value).__name__: _canonical(dataclasses.asdict(value))}",
        "        return {type(value).__name__: None}",
        ("tests/test_option_contract.py", "tests/test_cache.py"),
    ),
    Mutation(
        "cache-key-ignores-robust-params",
        "stochlap_torch/learning/cache.py",
        '{"params": params}, kind="multiscale_features")',
        '{"method": type(params).__name__}, kind="multiscale_features")',
        ("tests/test_option_contract.py", "tests/test_cache.py"),
    ),
    Mutation(
        "robust-batch-not-put-back-in-order",
        "stochlap_torch/robust/structure.py",
        "        else torch.cat([getattr(part, name) for part in parts])[order]",
        "        else torch.cat([getattr(part, name) for part in parts])",
        ("tests/test_robust_reference.py", "tests/test_robust.py"),
    ),
    Mutation(
        "transform-repr-names-only-the-variant",
        "stochlap_torch/learning/pyg.py",
        "f'variant={variant!r}', *changed, *attr",
        "f'variant={variant!r}', *attr",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "transform-truncates-to-integer-x",
        "stochlap_torch/learning/pyg.py",
        "            dtype = torch.promote_types(existing.dtype, features.dtype)",
        "            dtype = existing.dtype",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "robust-ignores-a-refused-option",
        "stochlap_torch/params.py",
        "    refuse_unused(variant, {name: value for name, value in given.items() if name not in "
        "accepted})",
        "    pass",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "paper-include-order-not-canonical",
        "stochlap_torch/params.py",
        "        _set(self, include=tuple(group for group in FEATURE_GROUPS if group in include))",
        "        _set(self, include=tuple(include))",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "interest-paper-mode-ignores-the-radius",
        "stochlap_torch/interest.py",
        '        refuse_unused(mode, {"radius": radius}, name="mode")',
        "        radius = None",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "explicit-cuda-backend-falls-back",
        "stochlap_torch/diffusion/engine.py",
        '        if asked == "cuda":  # insisted on: never a silent fallback',
        "        if False:",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "paper-features-ignore-a-structure",
        "stochlap_torch/features/__init__.py",
        '    refuse_unused("paper", {"structure": structure})',
        "    pass",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "layers-take-any-budget",
        "stochlap_torch/nn.py",
        "    return None if max_memory is None else resolve_budget(max_memory)",
        "    return max_memory",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "kernel-cache-keyed-on-its-own-folder-only",
        "stochlap_torch/_kernels/jit.py",
        "    return tuple(sorted({KERNELS_DIR, os.path.dirname(os.path.abspath(py_file))}))",
        "    return (os.path.dirname(os.path.abspath(py_file)),)",
        ("tests/test_kernel_cache.py",),
    ),
    Mutation(
        "umask-read-by-setting-it",
        "stochlap_torch/_common/files.py",
        '        with open("/proc/self/status", encoding="ascii") as status:',
        '        with open("/nonexistent/status", encoding="ascii") as status:',
        ("tests/test_cli_safety.py",),
    ),
    Mutation(
        "winding-flip-rotates-instead-of-reversing",
        "stochlap_torch/mesh/geometry.py",
        "    oriented = np.where(flip[:, None], faces[:, ::-1], faces)  # reversed, never rotated",
        "    oriented = np.where(flip[:, None], faces[:, [1, 2, 0]], faces)",
        ("tests/test_surface_invariance.py",),
    ),
    Mutation(
        "soups-not-refused",
        "stochlap_torch/mesh/geometry.py",
        "    if is_soup(faces):",
        "    if False:",
        ("tests/test_surface_invariance.py",),
    ),
    Mutation(
        "cache-serves-non-finite-features",
        "stochlap_torch/learning/cache.py",
        "    if not np.isfinite(features).all():",
        "    if False:",
        ("tests/test_cache_robustness.py", "tests/test_cache.py"),
    ),
    Mutation(
        "features-cli-removes-a-live-temporary",
        "stochlap_torch/learning/feature_files.py",
        "                if now - leftover.stat().st_mtime > STALE_SECONDS:",
        "                if True:",
        ("tests/test_cli_features.py",),
    ),
    Mutation(
        "robust-params-not-normalised",
        "stochlap_torch/params.py",
        "        object.__setattr__(params, name, value)",
        "            pass",
        ("tests/test_option_contract.py",),
    ),
    Mutation(
        "float32-spread-fields-rounded-before-the-first-term",
        "stochlap_torch/robust/heat.py",
        "    ordered = [fields.index_select(0, semigroup.order) for fields, _, _ in groups]\n",
        "    ordered = [fields.index_select(0, semigroup.order).to(dtype)"
        " for fields, _, _ in groups]\n",
        ("tests/test_robust_structure.py",),
    ),
    Mutation(
        "float32-spread-covariance-in-float32",
        "stochlap_torch/robust/channels.py",
        "    x, y, z = wide.unbind(dim=1)",
        "    x, y, z = centred.unbind(dim=1)",
        ("tests/test_robust_structure.py",),
    ),
    Mutation(
        "eigenvalue-gradient-off-diagonal-counted-once",
        "stochlap_torch/_common/tensors.py",
        "*(2.0 * weighted(k, (k + 1) % 3) for k in range(3))",
        "*(weighted(k, (k + 1) % 3) for k in range(3))",
        ("tests/test_symmetric_eigenvalues.py",),
    ),
    Mutation(
        "idt-refuses-the-loop-flip",
        "stochlap_torch/_kernels/geometry.py",
        "            if fa == fb:\n",
        "            if k == p or fa == fb:\n",
        ("tests/test_robust_parts.py",),
    ),
    Mutation(
        "idt-folded-quad-keeps-old-twins",
        "stochlap_torch/_kernels/geometry.py",
        "            tb2 = _moved(twin[b2], a1, a2, b1, b2, fa, fb)\n",
        "            tb2 = twin[b2]\n",
        ("tests/test_robust_parts.py",),
    ),
    Mutation(
        "idt-keeps-loops-in-the-laplacian",
        "stochlap_torch/_kernels/geometry.py",
        "    edge = rows != cols  # a loop moves nothing: x_i - x_i = 0\n",
        "    edge = rows == rows\n",
        ("tests/test_robust_parts.py",),
    ),
    Mutation(
        "match-points-ignores-votes-check",
        "stochlap_torch/evaluation/interest_metrics.py",
        "    weight = np.ones(num_truth) if votes is None else _votes(votes, num_truth)\n",
        "    weight = np.ones(num_truth) if votes is None else np.asarray(votes, dtype=float)\n",
        ("tests/test_evaluation.py",),
    ),
    Mutation(
        "twist-turns-the-other-way",
        "stochlap_torch/robust/channels.py",
        "torch.linalg.cross(shift[:, turns], shift[:, turns + 1], dim=2)",
        "torch.linalg.cross(shift[:, turns + 1], shift[:, turns], dim=2)",
        ("tests/test_robust_channels.py",),
    ),
    Mutation(
        "adjoint-recurrence-first-term-weight-sign",
        "stochlap_torch/robust/heat.py",
        "total.add_(later, alpha=2.0 if k % 2 == 1 else -2.0)",
        "total.add_(later, alpha=-2.0 if k % 2 == 1 else 2.0)",
        ("tests/test_robust_parts.py",),
    ),
    Mutation(
        "interpolation-transpose-in-row-order",
        "stochlap_torch/robust/pyramid.py",
        "                weights[by_corner.indices],",
        "                weights,",
        ("tests/test_robust_parts.py",),
    ),
]


def _scratch_copy(destination: Path) -> Path:
    """The repository's tracked and untracked-but-not-ignored files, plus the kernels' disk
    cache beside their sources (so the copy does not compile them again), under
    ``destination``."""
    command = ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"]
    listed = subprocess.run(command, cwd=ROOT, capture_output=True, check=True)
    names = listed.stdout.decode().split("\0")
    for name in filter(None, names):
        source = ROOT / name
        if source.is_file():
            target = destination / name
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)
    for cache in ROOT.glob("stochlap_torch/**/__pycache__"):
        shutil.copytree(cache, destination / cache.relative_to(ROOT), dirs_exist_ok=True)
    return destination


#: What :func:`_pytest` says of a run cut at its time limit: neither caught nor survived.
TIMEOUT = "<timeout>"


def _first_failure(output: str) -> str | None:
    match = re.search(r"^(?:FAILED|ERROR) (\S+)", output, flags=re.MULTILINE)
    return match.group(1) if match else None


def _pytest(copy: Path, selection: list[str], timeout: float) -> tuple[bool, str]:
    """``(passed, output)`` of ``pytest -x`` on ``selection`` in ``copy``."""
    environment = dict(os.environ, PYTHONPATH=str(copy), STOCHLAP_QUIET="1")
    command = [sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider", *selection]
    try:
        result = subprocess.run(
            command, cwd=copy, env=environment, capture_output=True, text=True, timeout=timeout
        )
    except subprocess.TimeoutExpired:
        return False, TIMEOUT
    return result.returncode == 0, result.stdout + result.stderr


def check(mutation: Mutation, copy: Path, timeout: float) -> tuple[str, str]:
    """``(outcome, detail)``: ``"caught"`` with the first failing test, ``"survived"``,
    ``"timeout"`` (a mutation that hangs the suite is not counted as caught), or ``"stale"``
    when the code it targets is gone."""
    path = copy / mutation.path
    source = path.read_text()
    if source.count(mutation.old) != 1:
        return "stale", f"{mutation.old!r} occurs {source.count(mutation.old)} times"
    path.write_text(source.replace(mutation.old, mutation.new))
    try:
        # Its likely catchers first (fast), then the whole default suite.
        for selection in ([list(mutation.tests)] if mutation.tests else []) + [[]]:
            passed, output = _pytest(copy, selection, timeout)
            if output == TIMEOUT:
                return "timeout", f"a run passed its {timeout:.0f} s limit (a hang?)"
            if not passed:
                return "caught", _first_failure(output) or output.strip().splitlines()[-1]
        return "survived", "the whole suite passed"
    finally:
        path.write_text(source)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("-k", default="", help="only mutations whose name contains this")
    parser.add_argument("--list", action="store_true", help="list the mutations and exit")
    parser.add_argument("--timeout", type=float, default=1800, help="seconds per pytest run")
    args = parser.parse_args(argv)
    chosen = [m for m in MUTATIONS if args.k in m.name]
    if args.list:
        print("\n".join(m.name for m in chosen))
        return 0
    outcomes = []
    with tempfile.TemporaryDirectory(prefix="stochlap-mutants-") as scratch:
        copy = _scratch_copy(Path(scratch))
        for mutation in chosen:
            start = time.perf_counter()
            outcome, detail = check(mutation, copy, args.timeout)
            outcomes.append(outcome)
            seconds = time.perf_counter() - start
            print(f"{outcome:8s} {mutation.name}: {detail} ({seconds:.0f} s)", flush=True)
    survived, stale = outcomes.count("survived"), outcomes.count("stale")
    timeouts = outcomes.count("timeout")
    caught = outcomes.count("caught")
    print(f"{caught} caught, {survived} survived, {timeouts} timed out, {stale} stale")
    return 1 if survived or timeouts else 2 if stale else 0


if __name__ == "__main__":
    sys.exit(main())

"""Hostile input and hostile environments (issues 15 and 16): each fixed item, tested.

Grouped by issue item. Every refusal is checked for its exact type (from
``stochlap_torch._common.errors``, or :class:`~stochlap_torch.diffusion.MemoryBudgetError`) and
for a message that names the problem; the meshes are tiny (``reference.noisy_sphere()``, 162
vertices), so each test takes well under a second unless it starts a fresh interpreter.
"""

from __future__ import annotations

import io
import os
import re
import resource
import shutil
import subprocess
import sys
import textwrap
import time
import tracemalloc
import zipfile
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh
from reference import icosphere, noisy_sphere

import stochlap_torch as sl
from stochlap_torch._common.errors import (
    FileFormatError,
    MeshError,
    ParameterError,
    StochlapError,
    UnsupportedInputError,
)
from stochlap_torch.cli import main as cli_main
from stochlap_torch.diffusion import MemoryBudgetError
from stochlap_torch.features import feature_settings
from stochlap_torch.mesh import validation

TESTS = Path(__file__).resolve().parent
PACKAGE = TESTS.parent / "stochlap_torch"


@pytest.fixture
def mesh() -> tuple[torch.Tensor, torch.Tensor]:
    """The jittered icosphere(2): 162 float64 vertices, no symmetric ties."""
    return noisy_sphere().tensors(torch.float64)


def _obj_text(vertices: np.ndarray, faces: np.ndarray, sep: str = " ") -> str:
    """An OBJ file of ``v`` and ``f`` records; ``sep`` follows the keyword."""
    lines = [f"v{sep}{float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in vertices]
    lines += [f"f{sep}{a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return "\n".join(lines) + "\n"


def _write_obj(path: Path, sep: str = " ") -> Path:
    small = icosphere(2)
    path.write_text(_obj_text(small.vertices, small.faces, sep))
    return path


def _run_cli(argv: list[str]) -> tuple[int, str]:
    """``stochlap argv`` in this process: (exit status, stderr)."""
    err, out = io.StringIO(), io.StringIO()
    with redirect_stderr(err), redirect_stdout(out):
        status = cli_main(argv)
    return status, err.getvalue()


def _ply_property(path: Path, name: str) -> np.ndarray:
    """A float vertex property of a PLY file, read by trimesh (independent of our writer)."""
    loaded = trimesh.load(path, process=False)
    return np.asarray(loaded.metadata["_ply_raw"]["vertex"]["data"][name], dtype=np.float64)


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


# ============================================================================================
# Issue 16, item 6: inputs that ended in a traceback and exit 1 (a huge OBJ face index,
# --threshold 1e-310) are one error line and exit 2, or a finite result.

HUGE_INDEX_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n"


def test_item6_huge_obj_face_index_is_a_mesh_error_naming_file_and_line(tmp_path):
    path = tmp_path / "huge.obj"
    path.write_text(HUGE_INDEX_OBJ)
    with pytest.raises(MeshError, match=re.escape(f"{path}:4")) as caught:
        sl.load_mesh(path)
    assert "99999999999999999999999" in str(caught.value)


def test_item6_huge_obj_face_index_through_the_cli_is_one_line_and_exit_2(tmp_path):
    path = tmp_path / "huge.obj"
    path.write_text(HUGE_INDEX_OBJ)
    status, err = _run_cli(["saliency", str(path), "--no-png", "-o", str(tmp_path / "o.ply")])
    assert status == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("stochlap: error: ")
    assert "huge.obj:4" in lines[0]
    assert not (tmp_path / "o.ply").exists()


def test_item6_denormal_threshold_is_a_finite_result_or_one_error_line(tmp_path):
    path = _write_obj(tmp_path / "sphere.obj")
    out = tmp_path / "o.ply"
    argv = ["saliency", str(path), "--no-png", "-o", str(out), "--threshold", "1e-310",
            "--variant", "paper"]  # fmt: skip
    status, err = _run_cli(argv)
    assert "Traceback" not in err
    assert status in (0, 2), err
    if status == 2:
        lines = [line for line in err.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("stochlap: error: "), err
        assert "threshold" in lines[0]
    else:
        values = _ply_property(out, "saliency")
        assert values.shape == (162,)
        assert np.isfinite(values).all()


# ============================================================================================
# Issue 16, item 7: interest_points(batch=...) looped over every label up to the largest.


def test_item7_interest_points_with_a_huge_batch_label_fails_at_once(mesh):
    vertices, faces = mesh
    saliency = sl.saliency(vertices, faces)
    batch = torch.zeros(vertices.shape[0], dtype=torch.int64)
    batch[-1] = 10**6
    start = time.perf_counter()
    with pytest.raises(MeshError, match="batch labels") as caught:
        sl.interest_points(saliency, vertices, faces, batch=batch)
    assert time.perf_counter() - start < 1.0
    assert "1000000" in str(caught.value)


# ============================================================================================
# Issue 16, item 8: archives are refused before trimesh unpacks them past the size limit.


def _zipped_obj(tmp_path: Path) -> Path:
    text = _write_obj(tmp_path / "member.obj").read_text()
    assert 8_000 < len(text) < 20_000  # a ~10 kB member
    archive = tmp_path / "meshes.zip"
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as handle:
        handle.writestr("member.obj", text)
    return archive


def test_item8_an_archive_over_the_size_limit_is_refused_naming_it(tmp_path, monkeypatch):
    archive = _zipped_obj(tmp_path)
    monkeypatch.delenv("STOCHLAP_MAX_ARCHIVE_BYTES", raising=False)
    assert sl.load_mesh(archive).num_vertices == 162  # under the default limit: it loads
    monkeypatch.setenv("STOCHLAP_MAX_ARCHIVE_BYTES", "1000")
    with pytest.raises(MeshError) as caught:
        sl.load_mesh(archive)
    message = str(caught.value)
    assert str(archive) in message
    assert "limit" in message and "STOCHLAP_MAX_ARCHIVE_BYTES" in message


# ============================================================================================
# Issue 16, item 9: a batch label of 10**8 allocated gigabytes; labels are checked first.


@pytest.mark.parametrize("label", [10**8, 10**9])
def test_item9_huge_batch_labels_fail_at_once_without_allocating(mesh, label):
    vertices, faces = mesh
    batch = torch.zeros(vertices.shape[0], dtype=torch.int64)
    batch[-1] = label
    max_rss_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    tracemalloc.start()
    start = time.perf_counter()
    try:
        with pytest.raises(MeshError, match="batch labels") as caught:
            sl.saliency(vertices, faces, batch=batch)
        elapsed = time.perf_counter() - start
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert str(label) in str(caught.value)
    assert elapsed < 1.0
    assert peak < 10 * 2**20, f"{peak / 2**20:.1f} MiB traced"
    # tracemalloc does not see torch's allocator: the process's peak resident size must not
    # have grown by a label-sized array either (10**8 int64 labels are 763 MiB).
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - max_rss_before
    assert grown < 256 * 2**10, f"peak RSS grew by {grown / 2**10:.0f} MiB"


# ============================================================================================
# Issue 16, item 10: every path has a budget; num_scales has a bound.


@pytest.mark.parametrize("variant", ["paper", "robust"])
def test_item10_a_million_scales_is_a_parameter_error(mesh, variant):
    vertices, faces = mesh
    with pytest.raises(ParameterError, match="num_scales"):
        sl.saliency(vertices, faces, num_scales=10**6, variant=variant)


def test_item10_robust_saliency_over_the_memory_budget(mesh):
    vertices, faces = mesh
    with pytest.raises(MemoryBudgetError, match="budget") as caught:
        sl.saliency(vertices, faces, max_memory=1000)
    assert isinstance(caught.value, StochlapError)


def test_item10_differentiable_operator_features_over_the_memory_budget(mesh):
    vertices, faces = mesh
    layer = sl.MultiscaleFeatures(variant="paper", differentiable_operator=True, max_memory=1000)
    with pytest.raises(MemoryBudgetError, match="budget") as caught:
        layer(vertices.clone().requires_grad_(True), faces)
    assert isinstance(caught.value, StochlapError)


# ============================================================================================
# Issue 16, item 12: unsupported dtypes and devices are one named error listing the dtypes.

ENTRY_POINTS = {
    "saliency_robust": lambda v, f: sl.saliency(v, f, variant="robust"),
    "saliency_paper": lambda v, f: sl.saliency(v, f, variant="paper"),
    "multiscale_features": lambda v, f: sl.multiscale_features(v, f),
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.complex64])
def test_item12_unsupported_vertex_dtypes_name_the_supported_ones(mesh, entry, dtype):
    vertices, faces = mesh
    with pytest.raises(UnsupportedInputError) as caught:
        ENTRY_POINTS[entry](vertices.to(dtype), faces)
    message = str(caught.value)
    assert "float32" in message and "float64" in message
    assert str(dtype).removeprefix("torch.") in message


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_item12_meta_vertices_name_the_supported_inputs(mesh, entry):
    vertices, faces = mesh
    with pytest.raises(UnsupportedInputError) as caught:
        ENTRY_POINTS[entry](vertices.to("meta"), faces)
    message = str(caught.value)
    assert "meta" in message
    assert "float32" in message and "float64" in message


def test_item12_saliency_of_the_wrong_type_is_a_parameter_error(mesh):
    vertices, faces = mesh
    with pytest.raises(ParameterError, match="saliency"):
        sl.interest_points("abc", vertices, faces)


@pytest.mark.parametrize("variant", ["robust", "paper"])
def test_item12_batch_of_the_wrong_type_is_a_named_error(mesh, variant):
    vertices, faces = mesh
    with pytest.raises(StochlapError, match="batch"):
        sl.saliency(vertices, faces, batch="x", variant=variant)


# ============================================================================================
# Issue 16, item 14: nan radius, fractional or boolean top_k are refused; numpy ints accepted.


@pytest.mark.parametrize(
    ("name", "value"), [("radius", float("nan")), ("top_k", 2.5), ("top_k", True)]
)
def test_item14_bad_interest_parameters_are_refused_by_name(mesh, name, value):
    vertices, faces = mesh
    saliency = sl.saliency(vertices, faces, variant="paper", num_scales=3)
    with pytest.raises(ParameterError, match=name):
        sl.interest_points(saliency, vertices, faces, **{name: value})


@pytest.mark.parametrize("variant", ["paper", "robust"])
def test_item14_numpy_integer_num_scales_equals_a_python_int(mesh, variant):
    vertices, faces = mesh
    expected = sl.saliency(vertices, faces, num_scales=8, variant=variant)
    got = sl.saliency(vertices, faces, num_scales=np.int64(8), variant=variant)
    assert torch.equal(got, expected)


def test_item14_numpy_integer_top_k_is_accepted(mesh):
    vertices, faces = mesh
    saliency = sl.saliency(vertices, faces, variant="paper", num_scales=3)
    expected = sl.interest_points(saliency, vertices, faces, top_k=3)
    assert torch.equal(sl.interest_points(saliency, vertices, faces, top_k=np.int64(3)), expected)


# ============================================================================================
# Issue 16, item 15: a tab after the OBJ keyword is whitespace; garbled numbers name file:line.


def test_item15_tab_after_the_obj_keyword_loads_like_a_space(tmp_path):
    spaces = sl.load_mesh(_write_obj(tmp_path / "spaces.obj", " "))
    tabs = sl.load_mesh(_write_obj(tmp_path / "tabs.obj", "\t"))
    assert tabs.num_vertices == 162
    assert torch.equal(tabs.vertices, spaces.vertices)
    assert torch.equal(tabs.faces, spaces.faces)


def test_item15_garbled_obj_number_names_file_and_line(tmp_path):
    lines = _write_obj(tmp_path / "spaces.obj").read_text().splitlines()
    lines[5] = "v 1.2.3 0 0"  # line 6
    path = tmp_path / "name.obj"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MeshError, match=r"name\.obj:6\b") as caught:
        sl.load_mesh(path)
    assert "1.2.3" in str(caught.value)


# ============================================================================================
# Issue 16, item 16: errors from dataset workers and truth files name the file.


def _good_and_broken(tmp_path: Path) -> tuple[Path, Path]:
    good = _write_obj(tmp_path / "good.obj")
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n")
    return good, broken


def test_item16_dataset_construction_error_names_the_broken_file(tmp_path):
    """MeshFeatureDataset computes every file's features at construction."""
    good, broken = _good_and_broken(tmp_path)
    with pytest.raises(MeshError, match=re.escape(str(broken))):
        sl.MeshFeatureDataset([good, broken], progress=False)


def test_item16_dataloader_worker_error_names_the_broken_file(tmp_path):
    """With ``in_memory=False`` each item is re-read in the worker: a file broken after
    construction fails there, and the error re-raised in the parent names it."""
    good, broken = _good_and_broken(tmp_path)
    _write_obj(broken)  # valid at construction
    dataset = sl.MeshFeatureDataset(
        [good, broken], cache_dir=tmp_path / "cache", in_memory=False, progress=False
    )
    broken.write_text("v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n")
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=None, num_workers=2, multiprocessing_context="fork", timeout=120
    )
    with pytest.raises(MeshError, match=re.escape(f"{broken}:3")):
        list(loader)


def test_item16_malformed_truth_file_names_the_file(tmp_path):
    from stochlap_torch.evaluation import read_marks

    path = tmp_path / "marks.txt"
    path.write_text("1 2 3\n4 x 5\n")
    with pytest.raises(FileFormatError, match=re.escape(f"{path}:2")):
        read_marks(path, num_vertices=100)


# ============================================================================================
# Issue 15, item 5: conventions (one rotation_invariant default, load_mesh(dtype=), validation
# once per unmodified mesh).


def test_issue15_item5_rotation_invariant_default_is_true_everywhere(tmp_path):
    """Every way to get the paper's features resolves ``rotation_invariant`` to True when it is
    not given (the robust channels are always invariant, and refuse the option)."""
    pytest.importorskip("torch_geometric", reason="StochasticFeatures needs torch_geometric")
    sphere = tmp_path / "sphere.obj"
    _write_obj(sphere)
    resolved = {
        "feature_settings": feature_settings("paper"),
        "MultiscaleFeatures": sl.MultiscaleFeatures(variant="paper").settings,
        "MeshFeatureDataset": sl.MeshFeatureDataset(
            [sphere], variant="paper", num_scales=2, progress=False
        ).settings,
        "StochasticFeatures": sl.StochasticFeatures(variant="paper").settings,
    }
    assert {name: s.rotation_invariant for name, s in resolved.items()} == dict.fromkeys(
        resolved, True
    )


def test_issue15_item5_load_mesh_dtype(tmp_path):
    path = _write_obj(tmp_path / "sphere.obj")
    single = sl.load_mesh(path, dtype=torch.float32)
    double = sl.load_mesh(path)
    assert single.vertices.dtype == torch.float32 and double.vertices.dtype == torch.float64
    assert torch.equal(single.vertices, double.vertices.float())
    assert torch.equal(single.faces, double.faces)
    with pytest.raises(StochlapError, match="dtype"):
        sl.load_mesh(path, dtype=torch.float16)


def test_issue15_item5_an_unmodified_mesh_is_validated_once(mesh, monkeypatch):
    calls = []
    check = validation._check

    def spy(*args, **kwargs):
        calls.append(1)
        return check(*args, **kwargs)

    monkeypatch.setattr(validation, "_check", spy)
    vertices, faces = mesh
    first = sl.saliency(vertices, faces, variant="paper")
    assert len(calls) >= 1
    calls.clear()
    assert torch.equal(sl.saliency(vertices, faces, variant="paper"), first)
    assert calls == []
    vertices.add_(0.0)  # an in-place change: the version counter moves
    sl.saliency(vertices, faces, variant="paper")
    assert len(calls) >= 1


# ============================================================================================
# Issue 15, item 4: the kernel cache falls back to a writable directory, else to no cache with
# a KernelCacheWarning; importing and calling the library never fails. Root ignores permission
# bits, so an unwritable path here is one under a regular file: makedirs fails for anyone.

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
    env.update(STOCHLAP_CACHE_DIR=str(blocked / "stochlap"), XDG_CACHE_HOME=str(blocked / "xdg"),
               TMPDIR=str(blocked / "tmp"), HOME=str(blocked / "home"),
               PYTHONDONTWRITEBYTECODE="1", STOCHLAP_QUIET="1")  # fmt: skip
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
    shutil.copytree(PACKAGE, root / "stochlap_torch",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))  # fmt: skip
    for folder in [root / "stochlap_torch", *(root / "stochlap_torch").rglob("*")]:
        if folder.is_dir():
            (folder / "__pycache__").write_text("")
    return root


def test_issue15_item4_library_works_with_no_writable_cache_directory_in_env(blocked):
    """The installed package (here an editable install: numba caches beside the sources
    first) imports and computes with every cache variable pointing nowhere."""
    result = _python("CALL = True\n" + textwrap.dedent(CACHE_SCRIPT), _cache_env(blocked))
    assert result.returncode == 0, result.stderr[-3000:]
    lines = result.stdout.splitlines()
    assert lines[0] == str(PACKAGE / "__init__.py")
    assert lines[2] == "True"


@pytest.mark.parametrize("fallback", ["STOCHLAP_CACHE_DIR", "TMPDIR"])
def test_issue15_item4_readonly_install_caches_in_the_first_writable_fallback(
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


def test_issue15_item4_readonly_install_without_any_cache_warns_and_computes(
    blocked, readonly_install
):
    env = _cache_env(blocked, PYTHONPATH=str(readonly_install), TEST_TEMPDIR=str(blocked))
    result = _python("CALL = True\n" + textwrap.dedent(CACHE_SCRIPT), env)
    assert result.returncode == 0, result.stderr[-3000:]
    package, directory, finite, warned = result.stdout.splitlines()
    assert package == str(readonly_install / "stochlap_torch" / "__init__.py")
    assert directory == "None"  # compiled uncached
    assert finite == "True"
    assert warned == "['KernelCacheWarning']"


# ============================================================================================
# Issue 15, item 1: the PyG transform in DataLoader workers (fork and spawn) gives the
# in-process features. A subprocess per start method, as in test_runtime.py.

PYG_SCRIPT = """
import sys

import torch
import trimesh
from torch_geometric.data import Data, Dataset
from torch_geometric.loader import DataLoader

import stochlap_torch as sl


class Shapes(Dataset):
    \"\"\"Small jittered ellipsoids; the transform computes the features, in the worker.\"\"\"

    def __init__(self, transform=None):
        super().__init__(None, transform=transform)

    def len(self):
        return 4

    def get(self, index):
        sphere = trimesh.creation.icosphere(2)
        pos = torch.tensor(sphere.vertices) * torch.tensor([1.0, 1.0 + 0.1 * index, 0.8])
        pos = pos + 0.01 * torch.sin(7.0 * pos[:, [1, 2, 0]])
        return Data(pos=pos, face=torch.tensor(sphere.faces).t().contiguous())


if __name__ == "__main__":
    data = Shapes(transform=sl.StochasticFeatures())
    expected = [data[i].x for i in range(len(data))]  # the parent uses the library first
    loader = DataLoader(data, batch_size=1, num_workers=2, multiprocessing_context=sys.argv[1],
                        timeout=200)
    got = [batch.x for batch in loader]
    same = len(got) == len(expected) and all(
        a.shape == b.shape and torch.equal(a, b) for a, b in zip(got, expected, strict=True)
    )
    print(same, expected[0].shape[1])
"""


@pytest.mark.parametrize(
    "method",
    ["fork", pytest.param("spawn", marks=pytest.mark.slow)],  # spawn: ~25 s loaded
)
def test_issue15_item1_pyg_transform_in_dataloader_workers(method, tmp_path):
    pytest.importorskip("torch_geometric", reason="torch_geometric is not installed")
    script = tmp_path / "pyg_loader.py"
    script.write_text(PYG_SCRIPT)
    result = subprocess.run(
        [sys.executable, str(script), method],
        capture_output=True,
        text=True,
        timeout=400,
        cwd=TESTS,
        check=False,
    )
    assert result.returncode == 0, result.stderr[-3000:]
    same, channels = result.stdout.split()
    assert same == "True"
    assert int(channels) == len(sl.StochasticFeatures().channel_names())

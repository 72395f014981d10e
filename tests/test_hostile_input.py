"""Hostile input: each is refused at once with a named error, or gives a finite result.

Every refusal is checked for its exact type (from ``stochlap_torch._common.errors``, or
:class:`~stochlap_torch.diffusion.MemoryBudgetError`) and for a message that names the problem;
the meshes are tiny (``reference.noisy_sphere()``, 162 vertices), so each test takes well under
a second.
"""

from __future__ import annotations

import io
import re
import resource
import time
import tracemalloc
import zipfile
from contextlib import redirect_stderr, redirect_stdout
from fractions import Fraction
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


# ============================================================================================
# A huge OBJ face index and a denormal --threshold: one error line and exit 2, or a finite
# result, never a traceback.

HUGE_INDEX_OBJ = "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 99999999999999999999999\n"


def test_huge_obj_face_index_is_a_mesh_error_naming_file_and_line(tmp_path):
    path = tmp_path / "huge.obj"
    path.write_text(HUGE_INDEX_OBJ)
    with pytest.raises(MeshError, match=re.escape(f"{path}:4")) as caught:
        sl.load_mesh(path)
    assert "99999999999999999999999" in str(caught.value)


def test_huge_obj_face_index_through_the_cli_is_one_error_line_and_exit_2(tmp_path):
    path = tmp_path / "huge.obj"
    path.write_text(HUGE_INDEX_OBJ)
    status, err = _run_cli(["saliency", str(path), "--no-png", "-o", str(tmp_path / "o.ply")])
    assert status == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("stochlap: error: ")
    assert "huge.obj:4" in lines[0]
    assert not (tmp_path / "o.ply").exists()


def test_denormal_threshold_is_a_finite_result_or_one_error_line(tmp_path):
    path = _write_obj(tmp_path / "sphere.obj")
    out = tmp_path / "o.ply"
    argv = ["saliency", str(path), "--no-png", "-o", str(out), "--threshold", "1e-310"]
    argv += ["--variant", "paper"]
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
# interest_points(batch=...) checks its labels before looping over them.


def test_interest_points_with_a_huge_batch_label_fails_at_once(mesh):
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
# Archives are refused before trimesh unpacks them past the size limit.


def _zipped_obj(tmp_path: Path) -> Path:
    text = _write_obj(tmp_path / "member.obj").read_text()
    assert 8_000 < len(text) < 20_000  # a ~10 kB member
    archive = tmp_path / "meshes.zip"
    with zipfile.ZipFile(archive, "w", compression=zipfile.ZIP_DEFLATED) as handle:
        handle.writestr("member.obj", text)
    return archive


def test_an_archive_over_the_size_limit_is_refused_naming_it(tmp_path, monkeypatch):
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
# Batch labels are checked before anything label-sized is allocated (10**8 would be GiB).


@pytest.mark.parametrize("label", [10**8, 10**9])
def test_huge_batch_labels_fail_at_once_without_allocating(mesh, label):
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
# Every path has a memory budget; num_scales has a bound.


@pytest.mark.parametrize("variant", ["paper", "robust"])
def test_a_million_scales_is_a_parameter_error(mesh, variant):
    vertices, faces = mesh
    with pytest.raises(ParameterError, match="num_scales"):
        sl.saliency(vertices, faces, num_scales=10**6, variant=variant)


def test_robust_saliency_over_the_memory_budget_is_refused(mesh):
    vertices, faces = mesh
    with pytest.raises(MemoryBudgetError, match="budget") as caught:
        sl.saliency(vertices, faces, max_memory=1000)
    assert isinstance(caught.value, StochlapError)


def test_differentiable_operator_features_over_the_memory_budget_are_refused(mesh):
    vertices, faces = mesh
    layer = sl.MultiscaleFeatures(variant="paper", differentiable_operator=True, max_memory=1000)
    with pytest.raises(MemoryBudgetError, match="budget") as caught:
        layer(vertices.clone().requires_grad_(True), faces)
    assert isinstance(caught.value, StochlapError)


# ============================================================================================
# Unsupported dtypes and devices are one named error listing the supported dtypes.

ENTRY_POINTS = {
    "saliency_robust": lambda v, f: sl.saliency(v, f, variant="robust"),
    "saliency_paper": lambda v, f: sl.saliency(v, f, variant="paper"),
    "multiscale_features": lambda v, f: sl.multiscale_features(v, f),
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.complex64])
def test_unsupported_vertex_dtypes_name_the_supported_ones(mesh, entry, dtype):
    vertices, faces = mesh
    with pytest.raises(UnsupportedInputError) as caught:
        ENTRY_POINTS[entry](vertices.to(dtype), faces)
    message = str(caught.value)
    assert "float32" in message and "float64" in message
    assert str(dtype).removeprefix("torch.") in message


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_meta_vertices_name_the_supported_inputs(mesh, entry):
    vertices, faces = mesh
    with pytest.raises(UnsupportedInputError) as caught:
        ENTRY_POINTS[entry](vertices.to("meta"), faces)
    message = str(caught.value)
    assert "meta" in message
    assert "float32" in message and "float64" in message


def test_saliency_of_the_wrong_type_is_a_parameter_error(mesh):
    vertices, faces = mesh
    with pytest.raises(ParameterError, match="saliency"):
        sl.interest_points("abc", vertices, faces)


@pytest.mark.parametrize("variant", ["robust", "paper"])
def test_batch_of_the_wrong_type_is_a_named_error(mesh, variant):
    vertices, faces = mesh
    with pytest.raises(StochlapError, match="batch"):
        sl.saliency(vertices, faces, batch="x", variant=variant)


# ============================================================================================
# A nan radius, a fractional or boolean top_k are refused; numpy integers are accepted.


@pytest.mark.parametrize(
    ("name", "value"), [("radius", float("nan")), ("top_k", 2.5), ("top_k", True)]
)
def test_bad_interest_parameters_are_refused_by_name(mesh, name, value):
    vertices, faces = mesh
    saliency = sl.saliency(vertices, faces, variant="paper", num_scales=3)
    with pytest.raises(ParameterError, match=name):
        sl.interest_points(saliency, vertices, faces, **{name: value})


@pytest.mark.parametrize("variant", ["paper", "robust"])
def test_numpy_integer_num_scales_equals_a_python_int(mesh, variant):
    vertices, faces = mesh
    expected = sl.saliency(vertices, faces, num_scales=8, variant=variant)
    got = sl.saliency(vertices, faces, num_scales=np.int64(8), variant=variant)
    assert torch.equal(got, expected)


def test_numpy_integer_top_k_equals_a_python_int(mesh):
    vertices, faces = mesh
    saliency = sl.saliency(vertices, faces, variant="paper", num_scales=3)
    expected = sl.interest_points(saliency, vertices, faces, top_k=3)
    assert torch.equal(sl.interest_points(saliency, vertices, faces, top_k=np.int64(3)), expected)


# ============================================================================================
# A tab after the OBJ keyword is whitespace; a garbled number names file:line.


def test_tab_after_the_obj_keyword_loads_like_a_space(tmp_path):
    spaces = sl.load_mesh(_write_obj(tmp_path / "spaces.obj", " "))
    tabs = sl.load_mesh(_write_obj(tmp_path / "tabs.obj", "\t"))
    assert tabs.num_vertices == 162
    assert torch.equal(tabs.vertices, spaces.vertices)
    assert torch.equal(tabs.faces, spaces.faces)


def test_garbled_obj_number_names_file_and_line(tmp_path):
    lines = _write_obj(tmp_path / "spaces.obj").read_text().splitlines()
    lines[5] = "v 1.2.3 0 0"  # line 6
    path = tmp_path / "name.obj"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(MeshError, match=r"name\.obj:6\b") as caught:
        sl.load_mesh(path)
    assert "1.2.3" in str(caught.value)


# ============================================================================================
# Errors from dataset construction, DataLoader workers and truth files name the file.


def _good_and_broken(tmp_path: Path) -> tuple[Path, Path]:
    good = _write_obj(tmp_path / "good.obj")
    broken = tmp_path / "broken.obj"
    broken.write_text("v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n")
    return good, broken


def test_dataset_construction_error_names_the_broken_file(tmp_path):
    """MeshFeatureDataset computes every file's features at construction."""
    good, broken = _good_and_broken(tmp_path)
    with pytest.raises(MeshError, match=re.escape(str(broken))):
        sl.MeshFeatureDataset([good, broken], progress=False)


def test_dataloader_worker_error_names_the_broken_file(tmp_path):
    """With ``in_memory=False`` each item is re-read in the worker: a file broken after
    construction fails there, and the error re-raised in the parent names it. One worker: it
    reads the good file, then the broken one."""
    good, broken = _good_and_broken(tmp_path)
    _write_obj(broken)  # valid at construction
    dataset = sl.MeshFeatureDataset(
        [good, broken], cache_dir=tmp_path / "cache", in_memory=False, progress=False
    )
    broken.write_text("v 0 0 0\nv 1 0 0\nv 0 1 zero\nf 1 2 3\n")
    loader = torch.utils.data.DataLoader(
        dataset, batch_size=None, num_workers=1, multiprocessing_context="fork", timeout=120
    )
    with pytest.raises(MeshError, match=re.escape(f"{broken}:3")):
        list(loader)


def test_malformed_truth_file_names_the_file(tmp_path):
    from stochlap_torch.evaluation import read_marks

    path = tmp_path / "marks.txt"
    path.write_text("1 2 3\n4 x 5\n")
    with pytest.raises(FileFormatError, match=re.escape(f"{path}:2")):
        read_marks(path, num_vertices=100)


HUGE = 10**400  # beyond every float: float(HUGE) raises OverflowError

#: name -> a call that gives that option ``HUGE``.
HUGE_OPTIONS = {
    "threshold": lambda v, f: sl.saliency(v, f, variant="paper", threshold=HUGE),
    "max_memory": lambda v, f: sl.saliency(v, f, variant="paper", max_memory=HUGE),
    "radius": lambda v, f: sl.interest_points(torch.rand(v.shape[0]), v, f, radius=HUGE),
    "t_global": lambda v, f: sl.interest_points(torch.rand(v.shape[0]), v, f, t_global=HUGE),
    "t0": lambda v, f: sl.saliency(v, f, robust=sl.RobustParams(t0=HUGE)),
    "min_vertices": lambda v, f: sl.saliency(v, f, robust=sl.RobustParams(min_vertices=HUGE)),
}


@pytest.mark.parametrize("name", sorted(HUGE_OPTIONS))
def test_an_option_beyond_the_float_range_is_a_parameter_error_naming_it(mesh, name):
    with pytest.raises(ParameterError, match=rf"^{name} "):
        HUGE_OPTIONS[name](*mesh)


@pytest.mark.parametrize(
    "value", [HUGE, -HUGE, 10**5000, Fraction(HUGE)], ids=["huge", "-huge", "longer", "fraction"]
)
def test_the_checks_name_a_number_too_large_for_a_float(value):
    from stochlap_torch._common.checks import check_int, check_number

    with pytest.raises(ParameterError, match=r"^size must be finite"):
        check_number("size", value)
    if isinstance(value, int):
        with pytest.raises(ParameterError, match=r"^count must "):
            check_int("count", value)
    with pytest.raises(ParameterError, match=r"^count must fit in 64 bits"):
        check_int("count", 2**63)

"""Bad meshes raise ``MeshError`` naming the problem; bad parameters raise ``ValueError``.

Every check is run through each public entry point, so none of them lets a bad mesh reach the
operators (where it would surface as NaN, Inf or an index error).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from reference import icosphere

import stochlap_torch as sl

EntryPoint = Callable[[torch.Tensor, torch.Tensor], object]

ENTRY_POINTS: dict[str, EntryPoint] = {
    "validate_mesh": sl.validate_mesh,
    "Mesh.validate": lambda v, f: sl.Mesh(v, f).validate(),
    "stochastic_laplacian": sl.stochastic_laplacian,
    "multiscale_representation": lambda v, f: sl.multiscale_representation(v, f, num_scales=3),
    "saliency": lambda v, f: sl.saliency(v, f, num_scales=3, variant="paper"),
    "StochasticLaplacian": lambda v, f: sl.StochasticLaplacian(num_scales=3)(v, f),
    "MultiscaleSaliency": lambda v, f: sl.MultiscaleSaliency(num_scales=3, variant="paper")(v, f),
}


def good_mesh() -> tuple[torch.Tensor, torch.Tensor]:
    """icosphere(1) as float64 / int64 tensors (42 vertices, 80 faces)."""
    return icosphere(1).tensors()


def with_nan() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    vertices[5, 1] = float("nan")
    return vertices, faces


def with_inf() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    vertices[7, 2] = float("inf")
    return vertices, faces


def quad_faces() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    return vertices, torch.cat([faces, faces[:, :1]], dim=1)


def flat_faces() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    return vertices, faces.reshape(-1)


def float_faces() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    return vertices, faces.to(torch.float64)


def negative_index() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    faces[3, 1] = -1
    return vertices, faces


def index_too_large() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    faces[4, 2] = vertices.shape[0]
    return vertices, faces


def repeated_vertex() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    faces[2, 2] = faces[2, 0]
    return vertices, faces


def zero_length_edge() -> tuple[torch.Tensor, torch.Tensor]:
    """Vertex 1 moved onto vertex 0, which it shares an edge with."""
    vertices, faces = good_mesh()
    a, b = (int(i) for i in faces[0, :2])
    vertices[b] = vertices[a]
    return vertices, faces


def empty_vertices() -> tuple[torch.Tensor, torch.Tensor]:
    return torch.zeros(0, 3, dtype=torch.float64), torch.zeros(0, 3, dtype=torch.int64)


def empty_faces() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, _ = good_mesh()
    return vertices, torch.zeros(0, 3, dtype=torch.int64)


def bad_vertex_shape() -> tuple[torch.Tensor, torch.Tensor]:
    vertices, faces = good_mesh()
    return vertices[:, :2], faces


#: name -> (builder, regular expressions that must all appear in the message)
BAD_MESHES = {
    "nan": (with_nan, [r"(?i)nan|non-finite", r"\b5\b"]),
    "inf": (with_inf, [r"(?i)inf|non-finite", r"\b7\b"]),
    "faces_F4": (quad_faces, [r"faces", r"(?i)shape|\(F, 3\)|triangle"]),
    "faces_1d": (flat_faces, [r"faces", r"(?i)shape|\(F, 3\)|triangle"]),
    "float_faces": (float_faces, [r"faces", r"(?i)integer"]),
    "negative_index": (negative_index, [r"(?i)outside|out of range|negative"]),
    "index_too_large": (index_too_large, [r"(?i)outside|out of range|>= ?V|42"]),
    "repeated_vertex": (repeated_vertex, [r"(?i)repeat|degenerate"]),
    "zero_length_edge": (zero_length_edge, [r"(?i)zero.length", r"(?i)merg", r"(?i)duplicate"]),
    "empty_vertices": (empty_vertices, [r"(?i)empty|no vertices"]),
    "empty_faces": (empty_faces, [r"(?i)empty|no faces"]),
    "vertex_shape": (bad_vertex_shape, [r"vertices", r"(?i)shape|\(V, 3\)"]),
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
@pytest.mark.parametrize("case", sorted(BAD_MESHES))
def test_bad_mesh_raises_mesh_error(case: str, entry: str) -> None:
    """Each bad mesh raises ``MeshError`` (a ``ValueError``) whose message names the problem."""
    builder, patterns = BAD_MESHES[case]
    vertices, faces = builder()
    with pytest.raises(sl.MeshError) as info:
        ENTRY_POINTS[entry](vertices, faces)
    assert isinstance(info.value, ValueError)
    message = str(info.value)
    for pattern in patterns:
        assert re.search(pattern, message), (pattern, message)


#: The layouts of neighbouring libraries (issue 33) -> the hint their error must carry.
OTHER_LAYOUTS = {
    "pyg_faces": (lambda v, f: (v, f.T), r"pass face\.T"),
    "batched_vertices": (lambda v, f: (v[None].expand(2, -1, -1), f), r"pack them with batch="),
    "batched_faces": (lambda v, f: (v, f[None]), r"pack them with batch="),
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
@pytest.mark.parametrize("layout", sorted(OTHER_LAYOUTS))
def test_other_libraries_layouts_get_a_hint(layout: str, entry: str) -> None:
    """PyG's ``(3, F)`` faces and batched ``(B, V, 3)`` tensors are refused with the fix."""
    change, hint = OTHER_LAYOUTS[layout]
    with pytest.raises(sl.MeshError, match=hint):
        ENTRY_POINTS[entry](*change(*good_mesh()))


def test_a_mesh_changed_without_a_version_bump_is_checked_again() -> None:
    """No validation is remembered between calls: a write through a numpy view (which moves
    no version counter) is seen by the next call."""
    vertices, faces = good_mesh()
    sl.validate_mesh(vertices, faces)
    vertices.numpy()[5, 1] = float("nan")
    with pytest.raises(sl.MeshError, match=r"non-finite"):
        sl.validate_mesh(vertices, faces)
    with pytest.raises(sl.MeshError, match=r"non-finite"):
        sl.saliency(vertices, faces, variant="paper")


def test_zero_length_edge_is_named_in_the_callers_numbering(monkeypatch) -> None:
    """Large meshes are renumbered before the weights (which catch zero-length edges) are
    built; the error must still name the caller's vertex indices."""
    from stochlap_torch.mesh import locality_order

    vertices, faces = zero_length_edge()
    a, b = sorted(int(i) for i in faces[0, :2])
    monkeypatch.setattr("stochlap_torch.mesh.ordering.LOCALITY_MIN_VERTICES", 1)
    assert not torch.equal(locality_order(vertices), torch.arange(len(vertices)))
    with pytest.raises(sl.MeshError, match=rf"\({a}, {b}\)"):
        sl.multiscale_representation(vertices, faces)


def test_good_mesh_passes_every_entry_point() -> None:
    """The unmodified mesh is accepted everywhere (so the failures above are the edits)."""
    vertices, faces = good_mesh()
    for entry in ENTRY_POINTS.values():
        entry(vertices, faces)


@pytest.mark.parametrize("num_scales", [1, 0, -3])
def test_num_scales_below_two(num_scales: int) -> None:
    """``num_scales < 2`` is a ``ValueError`` in the functions and the module constructors."""
    vertices, faces = good_mesh()
    with pytest.raises(ValueError, match="num_scales"):
        sl.multiscale_representation(vertices, faces, num_scales=num_scales)
    with pytest.raises(ValueError, match="num_scales"):
        sl.saliency(vertices, faces, num_scales=num_scales, variant="paper")
    with pytest.raises(ValueError, match="num_scales"):
        sl.StochasticLaplacian(num_scales=num_scales)
    with pytest.raises(ValueError, match="num_scales"):
        sl.MultiscaleSaliency(num_scales=num_scales, variant="paper")


@pytest.mark.parametrize("threshold", [0.0, 1.0, -1.0, 1.5])
def test_threshold_outside_open_unit_interval(threshold: float) -> None:
    """``threshold`` must lie in ``(0, 1)``."""
    vertices, faces = good_mesh()
    with pytest.raises(ValueError, match="threshold"):
        sl.multiscale_representation(vertices, faces, threshold=threshold)
    with pytest.raises(ValueError, match="threshold"):
        sl.saliency(vertices, faces, threshold=threshold, variant="paper")
    with pytest.raises(ValueError, match="threshold"):
        sl.StochasticLaplacian(threshold=threshold)
    with pytest.raises(ValueError, match="threshold"):
        sl.MultiscaleSaliency(threshold=threshold, variant="paper")


def memory_cases() -> dict[str, Callable[..., object]]:
    """Entry points that accept ``max_memory``."""
    return {
        "multiscale_representation": sl.multiscale_representation,
        "saliency": lambda *args, **kwargs: sl.saliency(*args, variant="paper", **kwargs),
    }


@pytest.mark.parametrize("entry", sorted(memory_cases()))
def test_run_over_budget_raises_memory_budget_error(entry: str) -> None:
    """A run over the budget fails up front.

    icosphere(4) has 2562 vertices; at ``K = 40`` its outputs alone (positions, coefficients
    and differences, about 5.7 MB) are over a 1 MB budget. The error must be a
    ``MemoryError`` subclass (not a bare ``MemoryError`` from an allocation) whose message
    says what to change.
    """
    vertices, faces = icosphere(4).tensors()
    function = memory_cases()[entry]
    with pytest.raises(MemoryError) as info:
        function(vertices, faces, num_scales=40, threshold=1e-3, max_memory=1 << 20)
    assert type(info.value) is not MemoryError
    assert issubclass(type(info.value), MemoryError)
    assert "num_scales" in str(info.value)


def test_tiny_threshold_over_budget_raises_when_operators_are_kept() -> None:
    """Kept operators with a threshold that lets ``F`` fill towards ``V x V`` fail up front.

    With ``lambda = 1e-12`` and ``K = 40`` every row of ``F`` on icosphere(4) would reach the
    whole mesh (about 100 MB per operator), far over a 16 MB budget that the outputs fit.
    """
    vertices, faces = icosphere(4).tensors()
    with pytest.raises(sl.MemoryBudgetError, match="threshold"):
        sl.multiscale_representation(
            vertices,
            faces,
            num_scales=40,
            threshold=1e-12,
            return_operators=True,
            max_memory=16 << 20,
        )


def test_memory_budget_error_from_modules() -> None:
    """The modules pass ``max_memory`` through (same error type as the functions)."""
    vertices, faces = icosphere(4).tensors()
    modules = [
        sl.StochasticLaplacian(num_scales=40, threshold=1e-12, max_memory=1 << 20),
        sl.MultiscaleSaliency(num_scales=40, threshold=1e-12, max_memory=1 << 20, variant="paper"),
    ]
    for module in modules:
        with pytest.raises(MemoryError) as info:
            module(vertices, faces)
        assert type(info.value) is not MemoryError


def test_tiny_threshold_within_budget_runs() -> None:
    """The budget check is not a blanket ban on small thresholds: a small mesh still runs."""
    vertices, faces = good_mesh()
    result = sl.multiscale_representation(vertices, faces, num_scales=8, threshold=1e-12)
    assert bool(torch.isfinite(result.positions).all())


def test_load_mesh_missing_file(tmp_path: Path) -> None:
    """A missing file is a ``FileNotFoundError``."""
    with pytest.raises(FileNotFoundError):
        sl.load_mesh(tmp_path / "nope.obj")


def test_load_mesh_without_faces(tmp_path: Path) -> None:
    """An OBJ with vertices but no faces is a ``MeshError``."""
    path = tmp_path / "points.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\n")
    with pytest.raises(sl.MeshError, match=r"(?i)face"):
        sl.load_mesh(path)


def test_load_mesh_with_duplicate_vertices_suggests_merging(tmp_path: Path) -> None:
    """Coincident vertices joined by an edge load (the robust variant takes them); the paper's
    method refuses them, suggesting ``merge_seams=True``."""
    path = tmp_path / "dup.obj"
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0]], dtype=float)
    lines = [f"v {x} {y} {z}" for x, y, z in points]
    lines += ["f 1 2 3", "f 1 3 4", "f 1 4 5", "f 2 5 3"]  # vertex 5 duplicates vertex 2
    path.write_text("\n".join(lines) + "\n")
    mesh = sl.load_mesh(path)
    assert mesh.num_vertices == 5
    with pytest.raises(sl.MeshError, match=r"(?i)merg"):
        sl.saliency(mesh.vertices, mesh.faces, variant="paper")
    merged = sl.load_mesh(path, merge_seams=True)
    assert merged.num_vertices == 4

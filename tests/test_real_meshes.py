"""Real meshes from ``../shared/meshes`` (skipped when absent) and the bundled ``spot``.

Each mesh stresses one defect listed in ``SOURCES.md``: bunny (open boundary, 1113
unreferenced vertices), octopus (4 components), squirrel (2 non-manifold edges), cow (a
pinched vertex). Counts from ``SOURCES.md`` are checked first so that a changed file cannot
silently turn a test into one about a different mesh.
"""

from __future__ import annotations

from functools import cache
from pathlib import Path

import numpy as np
import pytest
import reference as ref
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

import stochlap_torch as sl

NUM_SCALES = 6

#: file -> (V, F) as listed in SOURCES.md
EXPECTED_COUNTS = {
    "spot.obj": (2930, 5856),
    "cow.obj": (2903, 5804),
    "squirrel.off": (9995, 20000),
    "octopus.off": (16944, 33872),
    "bunny.obj": (35947, 69451),
}


@cache
def load_path(path: Path) -> sl.Mesh:
    """Load a mesh file once per session."""
    return sl.load_mesh(path)


@cache
def represent_path(path: Path) -> sl.MultiscaleRepresentation:
    """The float64 representation of a mesh file with its operators (cached)."""
    mesh = load_path(path)
    return sl.multiscale_representation(
        mesh.vertices, mesh.faces, num_scales=NUM_SCALES, return_operators=True
    )


class SharedMeshes:
    """Cached access to the files of ``../shared/meshes``."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder

    def path(self, name: str) -> Path:
        """Full path of ``name``; skips the test when that file is missing."""
        path = self.folder / name
        if not path.is_file():
            pytest.skip(f"real mesh {path} not found")
        return path

    def load(self, name: str) -> sl.Mesh:
        """The mesh ``name`` (cached)."""
        return load_path(self.path(name))

    def represent(self, name: str) -> sl.MultiscaleRepresentation:
        """The representation of ``name`` with its operators (cached)."""
        return represent_path(self.path(name))


@pytest.fixture
def shared(meshes_dir: Path) -> SharedMeshes:
    """The shared meshes (the ``meshes_dir`` fixture skips when the folder is absent)."""
    return SharedMeshes(meshes_dir)


def spot() -> sl.Mesh:
    """The bundled spot (byte-identical to ``../shared/meshes/spot.obj``)."""
    return load_path(sl.bundled_mesh_path("spot"))


def spot_representation() -> sl.MultiscaleRepresentation:
    """Representation of the bundled spot (cached)."""
    return represent_path(sl.bundled_mesh_path("spot"))


def row_sums(operator: torch.Tensor) -> torch.Tensor:
    """Row sums of a ``torch.sparse_csr`` matrix."""
    crow, values = operator.crow_indices(), operator.values()
    rows = torch.repeat_interleave(torch.arange(crow.numel() - 1), crow.diff())
    return values.new_zeros(crow.numel() - 1).index_add_(0, rows, values)


def components(mesh: sl.Mesh) -> np.ndarray:
    """Connected-component label of every vertex (isolated vertices are their own)."""
    edges = ref.unique_edges(mesh.faces.numpy())
    n = mesh.num_vertices
    graph = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1]


def referenced(mesh: sl.Mesh) -> np.ndarray:
    """``(V,)`` bool: used by at least one face."""
    mask = np.zeros(mesh.num_vertices, dtype=bool)
    mask[mesh.faces.numpy().ravel()] = True
    return mask


@pytest.mark.parametrize("name", sorted(EXPECTED_COUNTS))
def test_load_mesh_keeps_every_vertex(shared: SharedMeshes, name: str) -> None:
    """``load_mesh`` keeps every vertex in file order: counts match SOURCES.md."""
    mesh = shared.load(name)
    assert (mesh.num_vertices, mesh.num_faces) == EXPECTED_COUNTS[name]
    assert mesh.vertices.dtype == torch.float64
    assert mesh.faces.dtype == torch.int64


def test_load_obj_polygons_negative_indices_and_unused_vertices(tmp_path: Path) -> None:
    """OBJ parsing: ``v/vt/vn`` tokens, fan-triangulated quads, negative (relative) indices,
    and an unreferenced trailing vertex kept in place."""
    lines = ["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "vt 0 0", "vn 0 0 1"]
    lines += ["f 1/1/1 2/1/1 3/1/1 4/1/1"]
    lines += ["v 0 0 1", "v 1 0 1", "v 0 1 1", "f -3 -2 -1", "v 5 5 5"]
    path = tmp_path / "mixed.obj"
    path.write_text("\n".join(lines) + "\n")
    mesh = sl.load_mesh(path)
    assert mesh.num_vertices == 8
    np.testing.assert_array_equal(mesh.vertices[7].numpy(), [5.0, 5.0, 5.0])
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6]]


def test_bundled_spot_loads() -> None:
    """The bundled ``spot`` is found by name and loads to 2930 vertices in file order."""
    bundled = spot()
    assert (bundled.num_vertices, bundled.num_faces) == (2930, 5856)
    assert spot_representation().positions.shape == (NUM_SCALES, 2930, 3)


def test_bundled_spot_is_the_shared_spot(shared: SharedMeshes) -> None:
    """The bundled ``spot`` equals the shared copy vertex for vertex."""
    copy = shared.load("spot.obj")
    torch.testing.assert_close(spot().vertices, copy.vertices, rtol=0, atol=0)
    torch.testing.assert_close(spot().faces, copy.faces, rtol=0, atol=0)


def test_bunny_first_vertex_in_file_order(shared: SharedMeshes) -> None:
    """Vertex 0 of the bunny is the first ``v`` record of the file (no reordering)."""
    mesh = shared.load("bunny.obj")
    with shared.path("bunny.obj").open() as handle:
        first = next(line for line in handle if line.startswith("v "))
    expected = [float(x) for x in first.split()[1:4]]
    np.testing.assert_array_equal(mesh.vertices[0].numpy(), expected)


@pytest.mark.parametrize("name", sorted(EXPECTED_COUNTS))
def test_outputs_finite(shared: SharedMeshes, name: str) -> None:
    """Positions, coefficients, difference maps and saliency hold no NaN or Inf."""
    result = shared.represent(name)
    for tensor in (
        result.positions,
        result.coefficients,
        result.differences,
        result.saliency(),
    ):
        assert bool(torch.isfinite(tensor).all())


@pytest.mark.parametrize("name", sorted(EXPECTED_COUNTS))
def test_operator_rows_sum_to_one(shared: SharedMeshes, name: str) -> None:
    """Every ``F^(k)`` is row-stochastic on real meshes too."""
    for k, operator in enumerate(shared.represent(name).operators, 1):
        assert float(operator.values().min()) >= 0.0
        sums = row_sums(operator)
        torch.testing.assert_close(sums, torch.ones_like(sums), rtol=0, atol=1e-12, msg=f"k={k}")


@pytest.mark.parametrize("name", sorted(EXPECTED_COUNTS))
def test_reconstruction(shared: SharedMeshes, name: str) -> None:
    """Eq. 22 reconstructs the input to 1e-12 of the mesh size."""
    mesh, result = shared.load(name), shared.represent(name)
    scale = float(mesh.vertices.abs().max())
    torch.testing.assert_close(result.reconstruct(), mesh.vertices, rtol=0, atol=1e-12 * scale)


def test_bunny_unreferenced_vertices_keep_positions(shared: SharedMeshes) -> None:
    """The 1113 unreferenced bunny vertices stay put and get the minimum (finite) saliency."""
    mesh, result = shared.load("bunny.obj"), shared.represent("bunny.obj")
    unused = ~referenced(mesh)
    assert unused.sum() == 1113
    positions = result.positions.numpy()
    for k in range(NUM_SCALES):
        np.testing.assert_array_equal(positions[k][unused], mesh.vertices.numpy()[unused])
    saliency = result.saliency().numpy()
    assert np.isfinite(saliency).all()
    assert np.all(saliency[unused] == saliency[~unused].min())


def test_bunny_boundary_vertices_move(shared: SharedMeshes) -> None:
    """Open boundary: boundary vertices are still averaged with their neighbours (they move)."""
    mesh, result = shared.load("bunny.obj"), shared.represent("bunny.obj")
    faces = mesh.faces.numpy()
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    boundary = np.unique(undirected[counts == 1])
    assert len(undirected[counts == 1]) == 223
    moved = np.linalg.norm((result.positions[-1] - result.positions[0]).numpy()[boundary], axis=1)
    assert np.all(moved > 0)


def test_bunny_holes_give_no_interest_points_unless_asked(shared: SharedMeshes) -> None:
    """The bunny's open bottom: the paper saliency has 1-ring maxima on the rims of its holes;
    by default none of them is an interest point, with ``include_boundary`` they are back, and
    the points away from the rims are the same either way."""
    mesh, saliency = shared.load("bunny.obj"), shared.represent("bunny.obj").saliency()
    rim = ref.rim_vertices(mesh.num_vertices, mesh.faces.numpy())
    default = sl.interest_points(saliency, mesh.vertices, mesh.faces, mode="paper").tolist()
    asked = sl.interest_points(
        saliency, mesh.vertices, mesh.faces, mode="paper", include_boundary=True
    ).tolist()
    assert not set(default) & rim
    assert len(set(asked) & rim) >= 3
    assert set(default) <= set(asked) and set(asked) - set(default) <= rim


def test_octopus_components_do_not_mix(shared: SharedMeshes) -> None:
    """Octopus has 4 components; no ``F^(k)`` entry links vertices of different components."""
    mesh, result = shared.load("octopus.off"), shared.represent("octopus.off")
    labels = components(mesh)
    assert len(np.unique(labels)) == 4
    for k, operator in enumerate(result.operators, 1):
        crow, col = operator.crow_indices(), operator.col_indices()
        rows = torch.repeat_interleave(torch.arange(crow.numel() - 1), crow.diff())
        assert np.array_equal(labels[rows.numpy()], labels[col.numpy()]), f"F^({k}) mixes"


def test_squirrel_non_manifold_edges(shared: SharedMeshes) -> None:
    """Squirrel has 2 edges shared by more than 2 faces; unique edges are still counted once."""
    mesh = shared.load("squirrel.off")
    faces = mesh.faces.numpy()
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert int((counts > 2).sum()) == 2
    edges = sl.unique_edges(mesh.faces)
    assert edges.shape == undirected.shape
    np.testing.assert_array_equal(np.unique(edges.numpy(), axis=0), undirected)
    first = sl.stochastic_laplacian(mesh.vertices, mesh.faces)
    assert first.values().numel() == mesh.num_vertices + 2 * len(undirected)


def test_float32_on_real_mesh_close_to_float64() -> None:
    """float32 saliency on spot stays within 1e-4 of float64 (and is float32)."""
    mesh = spot()
    single = sl.saliency(mesh.vertices.float(), mesh.faces, num_scales=NUM_SCALES, variant="paper")
    double = spot_representation().saliency()
    assert single.dtype == torch.float32
    torch.testing.assert_close(single.double(), double, rtol=0, atol=1e-4)


def spot_patch(radius: float = 0.35) -> ref.SmallMesh:
    """The faces of spot within ``radius`` of vertex 0, keeping all vertices (most isolated).

    Keeping every vertex in place makes the patch a real-mesh test of isolated vertices too;
    only a few hundred vertices have edges, which the dense reference handles quickly.
    """
    mesh = sl.load_mesh(sl.bundled_mesh_path("spot"))
    vertices, faces = mesh.vertices.numpy(), mesh.faces.numpy()
    inside = np.linalg.norm(vertices - vertices[0], axis=1) < radius
    kept = faces[inside[faces].all(axis=1)]
    used = np.unique(kept)
    remap = np.full(len(vertices), -1)
    remap[used] = np.arange(len(used))
    extra = np.flatnonzero(~inside)[:5]  # a few isolated vertices as well
    sub_vertices = np.concatenate([vertices[used], vertices[extra]])
    return ref.SmallMesh("spot_patch", sub_vertices, remap[kept])


def test_spot_patch_matches_reference() -> None:
    """An irregular real patch (with boundary and isolated vertices) matches the reference."""
    patch = spot_patch()
    assert 100 < patch.vertices.shape[0] < 600
    expected = ref.multiscale(patch.vertices, patch.faces, num_scales=NUM_SCALES)
    vertices, faces = patch.tensors()
    result = sl.multiscale_representation(
        vertices, faces, num_scales=NUM_SCALES, return_operators=True
    )
    for got, want in zip(result.operators, expected.operators, strict=True):
        np.testing.assert_allclose(got.to_dense().numpy(), want, rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.positions.numpy(), expected.positions, rtol=0, atol=1e-10)
    np.testing.assert_allclose(result.saliency().numpy(), expected.saliency, rtol=0, atol=1e-10)


def test_save_ply_round_trip(tmp_path: Path) -> None:
    """``save_ply`` keeps every vertex in order, with colours and a scalar; load_mesh reads it."""
    mesh = spot()
    saliency = spot_representation().saliency()
    colors = np.full((mesh.num_vertices, 3), 200, dtype=np.uint8)
    path = sl.save_ply(
        tmp_path / "spot.ply", mesh.vertices, mesh.faces, colors=colors, scalars={"sal": saliency}
    )
    header = path.read_bytes().split(b"end_header")[0].decode("ascii")
    assert "property float sal" in header
    assert "property uchar red" in header
    assert f"element vertex {mesh.num_vertices}" in header
    back = sl.load_mesh(path)
    assert back.num_vertices == mesh.num_vertices
    torch.testing.assert_close(back.faces, mesh.faces, rtol=0, atol=0)
    torch.testing.assert_close(back.vertices, mesh.vertices.float().double(), rtol=0, atol=0)


def geodesic_from(mesh: sl.Mesh, sources: list[int]) -> np.ndarray:
    """``(len(sources), V)`` graph-geodesic distances along edges (scipy Dijkstra)."""
    edges = ref.unique_edges(mesh.faces.numpy())
    vertices = mesh.vertices.numpy()
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    n = mesh.num_vertices
    graph = coo_matrix((lengths, (edges[:, 0], edges[:, 1])), shape=(n, n)).tocsr()
    return dijkstra(graph, directed=False, indices=sources)


def test_interest_points_on_spot() -> None:
    """On spot: paper mode equals the reference; NMS points are far apart and sorted."""
    mesh = spot()
    saliency = spot_representation().saliency()
    paper = sl.interest_points(saliency, mesh.vertices, mesh.faces, mode="paper").tolist()
    assert paper == ref.interest_points_paper(saliency.numpy(), mesh.faces.numpy())
    radius = 0.08
    nms = sl.interest_points(saliency, mesh.vertices, mesh.faces, radius=radius).tolist()
    assert 1 <= len(nms) <= len(paper)
    assert set(nms) <= set(paper)
    assert bool(np.all(np.diff(saliency.numpy()[nms]) <= 0))
    limit = radius * ref.bbox_diagonal(mesh.vertices.numpy(), mesh.faces.numpy())
    distances = geodesic_from(mesh, nms)[:, nms]
    assert np.all(distances[~np.eye(len(nms), dtype=bool)] > limit)


@pytest.mark.slow
def test_large_mesh_200k(shared: SharedMeshes) -> None:
    """Slow: the 200k-vertex Loop-subdivided gargoyle, K = 8: finite, stochastic, reconstructs."""
    mesh = shared.load("gargoyle_loop1_200k.ply")
    result = sl.multiscale_representation(
        mesh.vertices, mesh.faces, num_scales=8, return_operators=True
    )
    assert bool(torch.isfinite(result.saliency()).all())
    for operator in result.operators:
        sums = row_sums(operator)
        torch.testing.assert_close(sums, torch.ones_like(sums), rtol=0, atol=1e-12)
    scale = float(mesh.vertices.abs().max())
    torch.testing.assert_close(result.reconstruct(), mesh.vertices, rtol=0, atol=1e-12 * scale)

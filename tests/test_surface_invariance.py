"""The same surface gives the same answer: a triangle soup (STL) loads as the
connected surface, and the robust variant does not depend on the faces' winding."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree
from scipy.stats import spearmanr

import stochlap_torch as sl
from stochlap_torch.mesh.geometry import TriangleSoupError, orient_faces
from stochlap_torch.robust import heat as heat_module
from stochlap_torch.robust.heat import heat_diagonal, heat_operator


@pytest.fixture(scope="module")
def spot() -> sl.mesh.Mesh:
    return sl.load_mesh(sl.mesh.bundled_mesh_path("spot"))


@pytest.fixture(scope="module")
def spot_stl(spot, tmp_path_factory):
    path = tmp_path_factory.mktemp("stl") / "spot.stl"
    trimesh.Trimesh(spot.vertices.numpy(), spot.faces.numpy(), process=False).export(path)
    return path


def _half_flipped(faces: torch.Tensor, seed: int = 0) -> torch.Tensor:
    chosen = torch.rand(faces.shape[0], generator=torch.Generator().manual_seed(seed)) < 0.5
    out = faces.clone()
    out[chosen] = out[chosen].flip(1)
    return out


def test_stl_loads_as_the_connected_surface(spot, spot_stl):
    soup = trimesh.load(spot_stl, process=False)  # every facet with its own three corners
    mesh = sl.load_mesh(spot_stl)
    assert (mesh.num_vertices, mesh.num_faces) == (spot.num_vertices, spot.num_faces)
    # The map back: every corner of the file is the merged vertex at its position.
    assert mesh.file_vertices.shape == (len(soup.vertices),)
    assert torch.equal(mesh.vertices[mesh.file_vertices], torch.from_numpy(soup.vertices))
    assert torch.equal(mesh.faces, mesh.file_vertices[torch.from_numpy(soup.faces)])
    # ... and the merged vertices are the OBJ's, rounded to STL's float32, one for one.
    single = spot.vertices.float().double().numpy()
    distance, match = cKDTree(single).query(mesh.vertices.numpy())
    assert distance.max() == 0.0 and np.unique(match).size == spot.num_vertices
    # A file that shares vertices keeps them as they are.
    assert sl.load_mesh(sl.mesh.bundled_mesh_path("spot")).file_vertices is None


def test_stl_gives_the_robust_saliency_of_the_obj(spot, spot_stl):
    mesh = sl.load_mesh(spot_stl)
    match = cKDTree(spot.vertices.numpy()).query(mesh.vertices.numpy())[1]
    expected = sl.saliency(spot.vertices, spot.faces).numpy()
    values = sl.saliency(mesh.vertices, mesh.faces).numpy()
    # Not identical: the STL rounds the positions to float32 and orders the vertices by
    # facet, and the decimation follows both in its ties (0.147 when loaded as a soup).
    assert spearmanr(values, expected[match])[0] > 0.99
    # Per corner of the file, through the map back.
    corners = torch.from_numpy(trimesh.load(spot_stl, process=False).vertices)
    corner_match = cKDTree(spot.vertices.numpy()).query(corners.numpy())[1]
    per_corner = values[mesh.file_vertices.numpy()]
    assert spearmanr(per_corner, expected[corner_match])[0] > 0.99


@pytest.mark.parametrize("change", ["reversed", "half_flipped"])
def test_robust_results_do_not_depend_on_the_winding(spot, change):
    faces = {"reversed": spot.faces.flip(1), "half_flipped": _half_flipped(spot.faces)}[change]
    assert torch.equal(sl.saliency(spot.vertices, faces), sl.saliency(spot.vertices, spot.faces))
    # Five scales: one twist (scale 3 to 4), whose outward normal must not follow the winding.
    assert "twist3" in sl.feature_channel_names(num_scales=5)
    expected = sl.multiscale_features(spot.vertices, spot.faces, num_scales=5)
    assert torch.equal(sl.multiscale_features(spot.vertices, faces, num_scales=5), expected)


def test_gradients_reach_the_vertices_of_a_mixed_winding(spot):
    vertices = spot.vertices.clone().requires_grad_(True)
    sl.multiscale_features(vertices, _half_flipped(spot.faces), num_scales=3).sum().backward()
    assert torch.isfinite(vertices.grad).all() and vertices.grad.abs().sum() > 0


def _outward(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Consistently wound with positive volume, by trimesh (a plain check)."""
    mesh = trimesh.Trimesh(vertices, faces, process=False)
    return bool(mesh.is_winding_consistent and mesh.volume > 0)


def _same_triangles(a: np.ndarray, b: np.ndarray) -> bool:
    return np.array_equal(np.sort(a, axis=1), np.sort(b, axis=1))


def test_orient_faces_is_canonical_and_outward():
    # Two spheres, one turned inside out, one with a third of its faces reversed.
    sphere = trimesh.creation.icosphere(2)
    vertices = np.concatenate([sphere.vertices, sphere.vertices * 0.5 + 3.0])
    faces = np.concatenate([sphere.faces[:, ::-1], sphere.faces + len(sphere.vertices)])
    faces[::3] = faces[::3, ::-1]
    oriented = orient_faces(vertices, faces)
    assert _same_triangles(oriented, faces)
    half = len(sphere.faces)
    assert _outward(vertices, oriented[:half]) and _outward(vertices, oriented[half:])
    # A face is reversed or kept, never rotated.
    kept = (oriented == faces).all(axis=1)
    assert (kept | (oriented == faces[:, ::-1]).all(axis=1)).all()
    for other in (faces[:, ::-1], sphere_faces_flipped(faces)):
        assert np.array_equal(orient_faces(vertices, np.ascontiguousarray(other)), oriented)


def sphere_faces_flipped(faces: np.ndarray) -> np.ndarray:
    out = faces.copy()
    out[1::2] = out[1::2, ::-1]
    return out


def test_orient_faces_leaves_a_consistently_outward_mesh_unchanged(spot):
    """Normal meshes keep their faces, so their robust results are those of before."""
    faces = spot.faces.numpy()
    assert np.array_equal(orient_faces(spot.vertices.numpy(), faces), faces)
    assert np.array_equal(orient_faces(spot.vertices.numpy(), faces[:, ::-1].copy()), faces)


def test_orient_faces_of_a_mobius_strip_does_not_depend_on_the_winding():
    count, vertices, faces = 24, [], []
    for i in range(count):
        angle = 2 * math.pi * i / count
        for s in (-0.3, 0.3):
            radius = 1 + s * math.cos(angle / 2)
            point = [radius * math.cos(angle), radius * math.sin(angle), s * math.sin(angle / 2)]
            vertices.append(point)
    for i in range(count):
        a, b = 2 * i, 2 * i + 1
        c, d = (2 * i + 2, 2 * i + 3) if i + 1 < count else (1, 0)  # the half twist
        faces += [[a, b, c], [b, d, c]]
    vertices, faces = np.array(vertices), np.array(faces)
    oriented = orient_faces(vertices, faces)
    assert _same_triangles(oriented, faces)
    for other in (faces[:, ::-1], sphere_faces_flipped(faces)):
        assert np.array_equal(orient_faces(vertices, np.ascontiguousarray(other)), oriented)


def test_a_triangle_soup_is_refused_before_any_eigen_solve(monkeypatch):
    sphere = trimesh.creation.icosphere(2)  # 320 faces, 960 corners as a soup
    vertices = torch.from_numpy(sphere.vertices[sphere.faces.reshape(-1)])
    faces = torch.arange(vertices.shape[0]).reshape(-1, 3)

    def no_eigsh(*args, **kwargs):
        raise AssertionError("an eigen solve ran on a triangle soup")

    monkeypatch.setattr("scipy.sparse.linalg.eigsh", no_eigsh)
    with pytest.raises(TriangleSoupError, match="triangle soup: 320 of its 320 faces"):
        sl.multiscale_features(vertices, faces)
    with pytest.raises(TriangleSoupError):
        sl.saliency(vertices, faces)


def _many_components() -> tuple[np.ndarray, np.ndarray]:
    """40 boxes (8 vertices each) of three sizes and one 642-vertex sphere."""
    box = trimesh.creation.box()
    sphere = trimesh.creation.icosphere(3)
    vertices, faces, offset = [], [], 0
    rng = np.random.default_rng(0)
    parts = [(box, 0.05 * (1 + i % 3)) for i in range(40)] + [(sphere, 1.0)]
    for part, size in parts:
        vertices.append(part.vertices * size + rng.normal(size=3) * 4)
        faces.append(part.faces + offset)
        offset += len(part.vertices)
    return np.concatenate(vertices), np.concatenate(faces)


def test_heat_diagonal_goes_component_by_component(monkeypatch):
    vertices, faces = _many_components()
    operator = heat_operator(vertices, faces)
    times = np.array([0.05, 0.2]) * float(operator.mass.sum())
    calls = []
    from scipy.sparse.linalg import eigsh as real_eigsh

    def counted(matrix, k, **kwargs):
        calls.append((matrix.shape[0], k))
        return real_eigsh(matrix, k=k, **kwargs)

    monkeypatch.setattr("scipy.sparse.linalg.eigsh", counted)
    values = heat_diagonal(operator, times)
    # A plain dense reference: every eigenpair of M^-1/2 L M^-1/2 of the whole level.
    scale = 1.0 / np.sqrt(operator.mass)
    dense = operator.laplacian.toarray() * scale[:, None] * scale[None, :]
    eigenvalues, basis = np.linalg.eigh(0.5 * (dense + dense.T))
    decay = np.exp(-np.maximum(eigenvalues, 0.0)[:, None] * times[None, :])
    expected = np.log(4 * np.pi * times * (basis**2 @ decay) / operator.mass[:, None])
    np.testing.assert_allclose(values, expected, atol=1e-5)
    # Only the sphere, the one component above the dense size, needs Lanczos: its own
    # eigenpairs, without the 40 zero eigenvalues of the others.
    assert calls and all(size == 642 for size, _ in calls), calls
    assert heat_module._DENSE_LEVEL < 642


def test_a_mostly_soup_file_loads_merged_like_a_full_soup(tmp_path):
    """The loader merges what the robust variant would refuse as a soup: more than half of the
    faces sharing no vertex, even when a few do (one definition of a soup for both)."""
    sphere = trimesh.creation.icosphere(1)
    corners = sphere.vertices[sphere.faces].reshape(-1, 3)  # every face its own corners
    faces = np.arange(corners.shape[0]).reshape(-1, 3)
    faces[1] = faces[0][[0, 2, 1]]  # two faces share their corners: not all are isolated
    path = tmp_path / "mostly_soup.ply"
    trimesh.Trimesh(corners, faces, process=False).export(path)
    mesh = sl.load_mesh(path)
    assert mesh.file_vertices is not None and mesh.num_vertices < corners.shape[0]
    sl.saliency(mesh.vertices, mesh.faces)  # a surface now, not a soup

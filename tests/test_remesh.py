"""Other triangulations of one surface (stochlap_torch.evaluation.remesh)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

import stochlap_torch as sl
from stochlap_torch._common.errors import MissingDependencyError, ParameterError
from stochlap_torch.evaluation import (
    compact,
    correspondence,
    decimate,
    isotropic_remesh,
    random_similarity,
)


@pytest.fixture(scope="module")
def spot():
    mesh = sl.load_mesh(sl.bundled_mesh_path())
    return mesh.vertices.numpy(), mesh.faces.numpy()


def _surface_samples(vertices, faces, steps=20):
    """Every triangle sampled on a barycentric grid of step ``1/steps``: ``(F * S, 3)``."""
    s = np.linspace(0.0, 1.0, steps + 1)
    u, v = np.meshgrid(s, s)
    keep = u + v <= 1.0 + 1e-12
    bary = np.stack([1 - u[keep] - v[keep], u[keep], v[keep]], axis=1)  # (S, 3)
    return np.einsum("sk,fkc->fsc", bary, vertices[faces]).reshape(-1, 3)


def test_compact_drops_degenerate_faces_and_unreferenced_vertices():
    vertices = np.arange(18, dtype=np.float64).reshape(6, 3)
    faces = np.array([[0, 2, 3], [1, 1, 4], [3, 2, 5]])
    v, f = compact(vertices, faces)
    assert v.tolist() == vertices[[0, 2, 3, 5]].tolist()
    assert f.tolist() == [[0, 1, 2], [2, 1, 3]]


def test_decimate_reaches_the_target_and_stays_on_the_surface(spot):
    v, f = spot
    vd, fd = decimate(v, f, len(v) // 3)
    assert abs(len(vd) - len(v) // 3) <= 0.05 * len(v)
    assert fd.min() >= 0 and fd.max() == len(vd) - 1
    distance = np.linalg.norm(correspondence(vd, v, f).points - vd, axis=1)
    assert distance.max() < 0.05 * np.linalg.norm(v.max(0) - v.min(0))


def test_correspondence_matches_a_naive_closest_point(spot):
    v, f = spot
    rng = np.random.default_rng(0)
    points = v[rng.choice(len(v), 20, replace=False)] + rng.normal(scale=0.01, size=(20, 3))
    found = correspondence(points, v, f)
    assert np.allclose(found.bary.sum(1), 1.0) and (found.bary >= -1e-12).all()
    samples = _surface_samples(v, f)
    for point, closest in zip(points, found.points, strict=True):
        # no sample of the surface is closer than the point found (samples lie on the mesh)
        best = np.linalg.norm(samples - point, axis=1).min()
        assert np.linalg.norm(point - closest) <= best + 1e-12


def test_transfer_is_exact_on_linear_functions_and_at_vertices(spot):
    v, f = spot
    c = correspondence(v, v, f)
    assert np.allclose(c.points, v, atol=1e-12)
    values = v @ np.array([1.0, -2.0, 0.5]) + 3.0
    assert np.allclose(c.transfer(values), values)
    rng = np.random.default_rng(1)
    bary = rng.dirichlet(np.ones(3), size=50)
    face = rng.choice(len(f), 50)
    inside = np.einsum("ij,ijc->ic", bary, v[f[face]])
    assert np.allclose(correspondence(inside, v, f).transfer(values), inside @ [1, -2, 0.5] + 3)


def test_random_similarity_is_a_proper_rotation_and_seeded():
    q, s, t = random_similarity(3)
    assert np.allclose(q @ q.T, np.eye(3)) and np.isclose(np.linalg.det(q), 1.0)
    assert 0.2 <= s <= 5.0 and t.shape == (3,)
    q2, s2, t2 = random_similarity(3)
    assert np.array_equal(q, q2) and s == s2 and np.array_equal(t, t2)


@pytest.mark.parametrize("bad", [3, 2.5, True, 10**9])
def test_bad_targets_are_named(spot, bad):
    v, f = spot
    with pytest.raises(ParameterError, match="num_vertices"):
        decimate(v, f, bad)


def test_isotropic_remesh_without_pyacvd_names_the_extra(spot, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyacvd", None)
    with pytest.raises(MissingDependencyError, match=r"stochlap_torch\[remesh\]"):
        isotropic_remesh(*spot, 1000)


def test_isotropic_remesh_gives_even_triangles_on_the_same_surface(spot):
    pytest.importorskip("pyacvd", reason="isotropic remeshing needs the remesh extra")
    v, f = spot
    vr, fr = isotropic_remesh(v, f, len(v))
    assert abs(len(vr) - len(v)) <= 0.02 * len(v)
    edges = np.linalg.norm(vr[fr[:, [1, 2, 0]]] - vr[fr], axis=2).ravel()
    source = np.linalg.norm(v[f[:, [1, 2, 0]]] - v[f], axis=2).ravel()
    assert edges.std() / edges.mean() < source.std() / source.mean()
    distance = np.linalg.norm(correspondence(vr, v, f).points - vr, axis=1)
    assert distance.max() < 0.02 * np.linalg.norm(v.max(0) - v.min(0))

"""The robust saliency and the per-mesh bookkeeping of a batch against plain implementations.

Each test here guards a family of plausible mistakes that still give believable numbers:
statistics weighted by vertex counts instead of areas (or over the whole batch instead of per
mesh, or over unreferenced vertices), a batch whose meshes are interleaved returned without its
results put back in order, an interest-point radius taken over vertices no face uses.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from reference import noisy_sphere, open_grid

import stochlap_torch as sl
from stochlap_torch.robust import (
    RobustParams,
    RobustRepresentation,
    robust_representation,
    robust_saliency,
)

PARAMS = RobustParams(num_scales=3)


def _reference_saliency(dn, mass, referenced, batch) -> np.ndarray:
    """Per mesh, loops: mean and deviation of every scale weighted by area over the
    referenced vertices; the positive part of the standardised value, averaged over scales."""
    out = np.zeros(dn.shape[0])
    for mesh in np.unique(batch):
        members = [i for i in range(dn.shape[0]) if batch[i] == mesh and referenced[i]]
        total = sum(mass[i] for i in members)
        for scale in range(dn.shape[1]):
            mean = sum(mass[i] * dn[i, scale] for i in members) / total
            variance = sum(mass[i] * (dn[i, scale] - mean) ** 2 for i in members) / total
            for i in members:
                out[i] += max(0.0, (dn[i, scale] - mean) / np.sqrt(variance)) / dn.shape[1]
    return out


def _synthetic(seed: int, interleaved: bool) -> RobustRepresentation:
    """Two meshes' worth of channels with uneven areas and a few unreferenced vertices."""
    rng = np.random.default_rng(seed)
    count, scales = 40, 3
    batch = np.repeat([0, 1], count // 2)
    if interleaved:
        batch = np.tile([1, 0], count // 2)
    mass = rng.uniform(0.01, 1.0, count) ** 3  # areas spread over three decades
    referenced = np.ones(count, dtype=bool)
    referenced[[3, 17, 30]] = False
    mass[~referenced] = 0.0
    dn = rng.normal(size=(count, scales)) + 5.0 * (batch == 1)[:, None]
    tensor = torch.from_numpy
    return RobustRepresentation(
        dn=tensor(dn),
        spread=None,
        twist=None,
        heat=None,
        mass=tensor(mass),
        referenced=tensor(referenced),
        params=RobustParams(num_scales=scales),
        batch=tensor(batch),
    )


@pytest.mark.parametrize("interleaved", [False, True], ids=["sorted", "interleaved"])
@pytest.mark.parametrize("seed", [0, 1])
def test_robust_saliency_matches_the_area_weighted_reference(seed, interleaved):
    rep = _synthetic(seed, interleaved)
    expected = _reference_saliency(
        rep.dn.numpy(), rep.mass.numpy(), rep.referenced.numpy(), rep.batch.numpy()
    )
    got = robust_saliency(rep)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-12, atol=1e-12)
    assert (got[~rep.referenced] == 0).all()


def test_robust_saliency_of_one_mesh_ignores_its_batch_neighbour():
    rep = _synthetic(0, interleaved=True)
    alone = RobustRepresentation(
        dn=rep.dn[rep.batch == 0],
        spread=None,
        twist=None,
        heat=None,
        mass=rep.mass[rep.batch == 0],
        referenced=rep.referenced[rep.batch == 0],
        params=rep.params,
    )
    torch.testing.assert_close(robust_saliency(rep)[rep.batch == 0], robust_saliency(alone))


def _plain_vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """A third of the area of every face at a vertex, over the total area."""
    areas = np.zeros(vertices.shape[0])
    for face in faces:
        a, b, c = vertices[face]
        area = 0.5 * np.linalg.norm(np.cross(b - a, c - a))
        for vertex in face:
            areas[vertex] += area / 3.0
    return areas / areas.sum()


def test_robust_mass_is_the_vertex_area_per_unit_total():
    mesh = noisy_sphere()
    vertices = mesh.vertices.copy()
    vertices[: len(vertices) // 2] *= 1.5  # uneven triangles
    rep = robust_representation(torch.tensor(vertices), torch.tensor(mesh.faces), PARAMS)
    np.testing.assert_allclose(
        rep.mass.numpy(), _plain_vertex_areas(vertices, mesh.faces), rtol=1e-10
    )


def _two_meshes():
    first, second = noisy_sphere(), open_grid()
    return [
        (torch.tensor(first.vertices), torch.tensor(first.faces)),
        (torch.tensor(second.vertices * 3.0 + 10.0), torch.tensor(second.faces)),
    ]


@pytest.mark.parametrize("layout", ["reversed", "interleaved"])
def test_a_batch_in_any_vertex_order_equals_separate_runs(layout):
    """The meshes' vertices may come in any order in a packed batch (labels not sorted):
    every channel, the saliency and the features come back at their own vertices."""
    meshes = _two_meshes()
    counts = [v.shape[0] for v, _ in meshes]
    labels = torch.repeat_interleave(torch.arange(2), torch.tensor(counts))
    if layout == "reversed":
        order = torch.cat([torch.arange(counts[0], sum(counts)), torch.arange(counts[0])])
    else:
        order = torch.argsort(torch.rand(sum(counts), generator=torch.Generator().manual_seed(0)))
    vertices = torch.cat([v for v, _ in meshes])[order]
    position = torch.argsort(order)  # where each original vertex went
    offsets = [0, counts[0]]
    faces = torch.cat([position[f + offsets[m]] for m, (_, f) in enumerate(meshes)])
    batch = labels[order]
    packed = robust_representation(vertices, faces, PARAMS, batch=batch)
    saliency = sl.saliency(vertices, faces, robust=PARAMS, batch=batch)
    features = sl.multiscale_features(vertices, faces, robust=PARAMS, batch=batch)
    for mesh, (v, f) in enumerate(meshes):
        mine = position[labels == mesh]  # the packed index of each of this mesh's vertices
        alone = robust_representation(v, f, PARAMS)
        for name in ("dn", "spread", "heat", "mass"):
            torch.testing.assert_close(getattr(packed, name)[mine], getattr(alone, name))
        torch.testing.assert_close(saliency[mine], sl.saliency(v, f, robust=PARAMS))
        torch.testing.assert_close(features[mine], sl.multiscale_features(v, f, robust=PARAMS))


@pytest.mark.parametrize("mode", ["nms", "paper"])
def test_interest_points_ignore_vertices_no_face_uses(mode):
    """An unreferenced vertex far away changes neither the radius nor the points."""
    mesh = noisy_sphere()
    vertices, faces = torch.tensor(mesh.vertices), torch.tensor(mesh.faces)
    saliency = sl.saliency(vertices, faces, robust=PARAMS)
    far = torch.cat([vertices, torch.tensor([[1e3, 1e3, 1e3]], dtype=vertices.dtype)])
    with_far = torch.cat([saliency, saliency.max()[None] * 2])
    for radius in (0.05, 0.2, 0.5) if mode == "nms" else (None,):
        alone = sl.interest_points(saliency, vertices, faces, mode=mode, radius=radius)
        extra = sl.interest_points(with_far, far, faces, mode=mode, radius=radius)
        assert torch.equal(alone, extra)

"""Per-vertex multiscale features: layout, invariances, batches, gradients."""

from __future__ import annotations

import math

import pytest
import torch
from reference import SMALL_MESH_BUILDERS, icosphere, noisy_sphere

import stochlap_torch as sl
from stochlap_torch.features import (
    feature_channel_names,
    mesh_lengths,
    multiscale_features,
)
from stochlap_torch.mesh import vertex_normals
from stochlap_torch.nn import MultiscaleFeatures

K = 4


def _mesh(name="noisy_sphere"):
    mesh = SMALL_MESH_BUILDERS[name]()
    return torch.tensor(mesh.vertices), torch.tensor(mesh.faces)


def _rotation(seed: int = 0) -> torch.Tensor:
    q, r = torch.linalg.qr(
        torch.randn(3, 3, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    )
    q = q * torch.sign(torch.diagonal(r))
    return q if torch.det(q) > 0 else -q


def test_channel_layout_and_values():
    vertices, faces = _mesh()
    layer = MultiscaleFeatures(num_scales=K, rotation_invariant=False, variant="paper")
    names = layer.channel_names()
    features = layer(vertices, faces)
    assert features.shape == (vertices.shape[0], layer.num_channels) == (162, 5 * (K - 1) + 1)
    assert len(set(names)) == len(names)
    assert names[:4] == ["coef2_x", "coef2_y", "coef2_z", "coef3_x"]
    assert names[-1] == "saliency"
    rep = sl.multiscale_representation(vertices, faces, K)
    mean_edge = mesh_lengths(vertices, faces)[0]
    column = {name: features[:, i] for i, name in enumerate(names)}
    torch.testing.assert_close(column["coef3_y"], rep.coefficients[2, :, 1] / mean_edge)
    torch.testing.assert_close(column["coef4_norm"], rep.coefficients[3].norm(dim=1) / mean_edge)
    torch.testing.assert_close(column["diff3"], rep.differences[2])
    torch.testing.assert_close(column["saliency"], rep.saliency())


def test_rotation_invariant_layout_and_pythagoras():
    vertices, faces = _mesh()
    layer = MultiscaleFeatures(num_scales=K, rotation_invariant=True, variant="paper")
    names = layer.channel_names()
    features = layer(vertices, faces)
    assert names[:2] == ["coef2_normal", "coef2_tangent"]
    column = {name: features[:, i] for i, name in enumerate(names)}
    for k in range(2, K + 1):
        squared = column[f"coef{k}_normal"] ** 2 + column[f"coef{k}_tangent"] ** 2
        torch.testing.assert_close(squared, column[f"coef{k}_norm"] ** 2)
    # On a sphere smoothing pulls vertices inwards, so C = P^(k-1) - P^(k) points outwards.
    assert (column["coef3_normal"] > 0).float().mean() > 0.9


@pytest.mark.parametrize("normalisation", ["mean_edge", "bbox_diagonal"])
def test_rotation_invariant_features_are_similarity_invariant(normalisation):
    vertices, faces = _mesh()
    layer = MultiscaleFeatures(
        num_scales=K, rotation_invariant=True, normalisation=normalisation, variant="paper"
    )
    moved = 3.7 * vertices @ _rotation().T + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    # bbox diagonal is not rotation invariant: check scale + translation only for it
    if normalisation == "bbox_diagonal":
        moved = 3.7 * vertices + torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    torch.testing.assert_close(layer(moved, faces), layer(vertices, faces), rtol=1e-9, atol=1e-10)


def test_xyz_features_rotate_with_the_mesh():
    vertices, faces = _mesh()
    rotation = _rotation(3)
    layer = MultiscaleFeatures(
        num_scales=K, include=("coefficients",), rotation_invariant=False, variant="paper"
    )
    base = layer(vertices, faces).reshape(-1, K - 1, 3)
    moved = layer(2.0 * vertices @ rotation.T, faces).reshape(-1, K - 1, 3)
    torch.testing.assert_close(moved, base @ rotation.T, rtol=1e-9, atol=1e-10)


def test_unnormalised_coefficients_scale_with_the_mesh():
    vertices, faces = _mesh()
    layer = MultiscaleFeatures(
        num_scales=K, include=("norms",), normalisation="none", variant="paper"
    )
    torch.testing.assert_close(layer(2.0 * vertices, faces), 2.0 * layer(vertices, faces))


def test_batch_equals_separate_runs():
    meshes = [_mesh("noisy_sphere"), _mesh("open_grid"), _mesh("unreferenced_vertex")]
    meshes[1] = (meshes[1][0] * 10.0, meshes[1][1])  # a different size per mesh
    packed = sl.MeshBatch.from_meshes(meshes)
    for normalisation in ("mean_edge", "bbox_diagonal"):
        layer = MultiscaleFeatures(
            num_scales=K, rotation_invariant=True, normalisation=normalisation, variant="paper"
        )
        together = packed.unbatch(layer(packed.vertices, packed.faces, packed.batch))
        for (vertices, faces), got in zip(meshes, together, strict=True):
            torch.testing.assert_close(got, layer(vertices, faces), rtol=1e-10, atol=1e-12)


def test_vertex_normals_on_a_sphere_point_outwards():
    sphere = icosphere(2)
    vertices = torch.tensor(sphere.vertices)
    normals = vertex_normals(vertices, torch.tensor(sphere.faces))
    radial = vertices / vertices.norm(dim=1, keepdim=True)
    assert (normals * radial).sum(dim=1).min() > 0.999
    torch.testing.assert_close(normals.norm(dim=1), torch.ones(len(vertices), dtype=torch.float64))


def test_mesh_lengths_per_mesh():
    vertices, faces = _mesh("icosphere1")
    packed = sl.MeshBatch.from_meshes([(vertices, faces), (4.0 * vertices, faces)])
    diagonal = mesh_lengths(packed.vertices, packed.faces, packed.batch, "bbox_diagonal")
    expected = (vertices.max(0).values - vertices.min(0).values).norm()
    torch.testing.assert_close(diagonal, torch.stack([expected, 4.0 * expected]))
    edge = mesh_lengths(packed.vertices, packed.faces, packed.batch, "mean_edge")
    assert math.isclose(float(edge[1] / edge[0]), 4.0, rel_tol=1e-12)


def test_gradients_are_finite_with_an_unreferenced_vertex():
    vertices, faces = _mesh("unreferenced_vertex")
    for differentiable in (False, True):
        points = vertices.clone().requires_grad_(True)
        layer = MultiscaleFeatures(
            num_scales=3,
            rotation_invariant=True,
            differentiable_operator=differentiable,
            variant="paper",
        )
        layer(points, faces).square().sum().backward()
        assert torch.isfinite(points.grad).all() and points.grad.abs().sum() > 0


def test_differentiable_operator_gives_the_same_features():
    vertices, faces = torch.tensor(noisy_sphere().vertices), torch.tensor(noisy_sphere().faces)
    plain = multiscale_features(vertices, faces, num_scales=K, variant="paper")
    through = multiscale_features(
        vertices, faces, num_scales=K, differentiable_operator=True, variant="paper"
    )
    torch.testing.assert_close(through, plain, rtol=0, atol=1e-12)


def test_float32():
    vertices, faces = _mesh()
    features = MultiscaleFeatures(num_scales=K, rotation_invariant=True, variant="paper")(
        vertices.float(), faces
    )
    assert features.dtype == torch.float32 and torch.isfinite(features).all()


@pytest.mark.parametrize(
    "kwargs",
    [
        {"include": ("coefficients", "colour")},
        {"include": ()},
        {"normalisation": "area"},
        {"num_scales": 1},
    ],
)
def test_bad_parameters(kwargs):
    with pytest.raises(ValueError):
        MultiscaleFeatures(variant="paper", **kwargs)


def test_channel_names_match_function():
    names = feature_channel_names(
        variant="paper", num_scales=3, include=("saliency", "differences")
    )
    assert names == ["diff2", "diff3", "saliency"]  # groups always in FEATURE_GROUPS order

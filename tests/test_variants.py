"""Saliency variants (stochlap_torch.variants): definitions, invariances, valence bias."""

from __future__ import annotations

import math

import numpy as np
import pytest
import reference as ref
import torch
from reference import icosphere, to_numpy, two_components
from scipy.stats import spearmanr

import stochlap_torch as sl
from stochlap_torch.mesh import (
    outward_sign,
    vertex_normals,
    vertex_valence,
)
from stochlap_torch.mesh import (
    vertex_mean_edge_length as mean_edge_length,
)
from stochlap_torch.saliency_maps import (
    DEFAULT_VARIANT,
    VARIANTS,
    valence_normalised_differences,
)

NEW_VARIANTS = [v for v in VARIANTS if v != "paper"]


@pytest.fixture(scope="module")
def spot() -> sl.Mesh:
    """The bundled cow (2930 vertices, valences 4..8: an irregular triangulation)."""
    return sl.load_mesh(sl.bundled_mesh_path("spot"))


def _tensors(mesh) -> tuple[torch.Tensor, torch.Tensor]:
    return torch.from_numpy(mesh.vertices), torch.from_numpy(mesh.faces)


def _saliency(vertices, faces, variant: str, **options) -> torch.Tensor:
    return sl.mesh_saliency(vertices, faces, variant=variant, **options)


def _rotation(seed: int = 3) -> torch.Tensor:
    q, _ = torch.linalg.qr(
        torch.randn(3, 3, generator=torch.Generator().manual_seed(seed)).double()
    )
    return q * torch.sign(torch.linalg.det(q))


def test_paper_variant_is_algorithm_2(bumpy):
    """The paper variant is Algorithm 2 of the dense reference, and the default scales."""
    vertices, faces = _tensors(bumpy)
    expected = ref.multiscale(bumpy.vertices, bumpy.faces, num_scales=6).saliency
    got = _saliency(vertices, faces, "paper", num_scales=6)
    np.testing.assert_allclose(got.numpy(), expected, rtol=1e-9, atol=1e-12)
    default = ref.multiscale(bumpy.vertices, bumpy.faces).saliency
    np.testing.assert_allclose(
        _saliency(vertices, faces, "paper").numpy(), default, rtol=1e-9, atol=1e-12
    )


@pytest.mark.parametrize("variant", VARIANTS)
def test_finite_with_unreferenced_vertex_and_components(variant, small_mesh):
    vertices, faces = _tensors(small_mesh)
    saliency = _saliency(vertices, faces, variant, num_scales=5)
    assert saliency.shape == (vertices.shape[0],)
    assert saliency.dtype == torch.float64
    assert bool(torch.isfinite(saliency).all())


@pytest.mark.parametrize("variant", NEW_VARIANTS)
def test_invariant_to_rotation_translation_and_scale(variant, bumpy):
    vertices, faces = _tensors(bumpy)
    moved = 7.5 * vertices @ _rotation().T + torch.tensor([3.0, -2.0, 11.0], dtype=torch.float64)
    before = _saliency(vertices, faces, variant, num_scales=6)
    after = _saliency(moved, faces, variant, num_scales=6)
    torch.testing.assert_close(after, before, rtol=1e-7, atol=1e-9)


def test_normal_displacement_ignores_face_orientation(bumpy):
    vertices, faces = _tensors(bumpy)
    flipped = faces[:, [0, 2, 1]]
    torch.testing.assert_close(
        _saliency(vertices, flipped, "normal_displacement"),
        _saliency(vertices, faces, "normal_displacement"),
    )
    assert float(outward_sign(vertices, faces)[0]) == 1.0
    assert float(outward_sign(vertices, flipped)[0]) == -1.0


@pytest.mark.parametrize("variant", ["normal_coefficients", "normal_displacement"])
def test_a_bump_on_a_sphere_is_the_most_salient_region(variant):
    sphere = icosphere(3)  # 642 vertices, all equivalent but for valence 5 / 6
    vertices, faces = _tensors(sphere)
    tip = 100
    vertices = vertices.clone()
    vertices[tip] *= 1.25
    saliency = _saliency(vertices, faces, variant, num_scales=6)
    ring = set(faces[(faces == tip).any(dim=1)].flatten().tolist())
    assert int(saliency.argmax()) in ring
    # and the map is highest at the tip itself, not on the valence-5 vertices.
    assert int(saliency.argmax()) == tip


def test_valence_bias_is_lower_than_the_paper_mode_on_an_irregular_mesh(spot):
    vertices, faces = spot.vertices.double(), spot.faces
    valence = to_numpy(vertex_valence(faces, vertices.shape[0]))
    assert valence.min() <= 4 and valence.max() >= 8  # irregular
    rep = sl.multiscale_representation(vertices, faces, 8, 1e-3)
    from stochlap_torch.saliency_maps import saliency_from_representation

    rho = {
        v: abs(
            spearmanr(to_numpy(saliency_from_representation(rep, vertices, faces, v)), valence)[0]
        )
        for v in VARIANTS
        if v != "robust"  # its own representation: see test_robust.py
    }
    assert rho["paper"] > 0.1
    assert rho["valence_normalised"] < 0.05
    assert rho["normal_coefficients"] < rho["paper"] / 2
    assert rho["normal_displacement"] < 0.6 * rho["paper"]


def test_valence_normalised_maps_have_unit_median_per_valence():
    differences = torch.tensor([[0.0] * 6, [1.0, 3.0, 2.0, 10.0, 20.0, 30.0]], dtype=torch.float64)
    valence = torch.tensor([5, 5, 5, 6, 6, 6])
    out = valence_normalised_differences(differences, valence, min_count=3)
    torch.testing.assert_close(out[1], torch.tensor([0.5, 1.5, 1.0, 0.5, 1.0, 1.5]).double())
    # A valence held by too few vertices borrows the nearest populated valence's median.
    valence = torch.tensor([5, 5, 5, 6, 6, 7])
    out = valence_normalised_differences(differences, valence, min_count=2)
    assert math.isclose(float(out[1, 5]), 30.0 / 10.0)  # lower median of {10, 20}
    with pytest.raises(ValueError, match="min_count"):
        valence_normalised_differences(differences, valence, min_count=0)


def test_batch_equals_separate_runs():
    first = icosphere(2)
    second = two_components()
    vertices = torch.cat([torch.from_numpy(first.vertices), torch.from_numpy(second.vertices)])
    faces = torch.cat(
        [torch.from_numpy(first.faces), torch.from_numpy(second.faces) + first.vertices.shape[0]]
    )
    batch = torch.cat(
        [torch.zeros(first.vertices.shape[0]), torch.ones(second.vertices.shape[0])]
    ).long()
    for variant in VARIANTS:
        packed = _saliency(vertices, faces, variant, num_scales=5, batch=batch)
        alone = [_saliency(*_tensors(mesh), variant, num_scales=5) for mesh in (first, second)]
        torch.testing.assert_close(packed, torch.cat(alone), rtol=1e-10, atol=1e-12)


def test_helpers_on_a_sphere():
    sphere = icosphere(2)
    vertices, faces = _tensors(sphere)
    normals = vertex_normals(vertices, faces)
    cosine = (normals * vertices / vertices.norm(dim=1, keepdim=True)).sum(dim=1)
    assert float(cosine.min()) > 0.99
    lengths = mean_edge_length(vertices, faces)
    assert float(lengths.min()) > 0 and float(lengths.max() / lengths.min()) < 1.5
    valence = vertex_valence(faces, vertices.shape[0])
    assert sorted(np.unique(to_numpy(valence)).tolist()) == [5, 6]
    assert int((valence == 5).sum()) == 12


def test_bad_arguments(bumpy):
    vertices, faces = _tensors(bumpy)
    with pytest.raises(ValueError, match="variant"):
        _saliency(vertices, faces, "nope")
    with pytest.raises(ValueError):
        _saliency(vertices, faces, "normal_coefficients", num_scales=1)


def test_library_option_matches_the_layer(bumpy):
    """``mesh_saliency(..., variant=)`` and ``MultiscaleSaliency(variant=)`` agree bitwise."""
    vertices, faces = _tensors(bumpy)
    for variant in VARIANTS:
        expected = sl.mesh_saliency(vertices, faces, num_scales=5, variant=variant)
        module = sl.MultiscaleSaliency(num_scales=5, variant=variant)(vertices, faces)
        assert torch.equal(module, expected)
    with pytest.raises(ValueError, match="variant"):
        sl.MultiscaleSaliency(variant="nope")


def test_the_default_variant_is_robust_and_an_options_object_names_its_method(bumpy):
    """Without ``variant=``: the robust saliency, or the method of a ``params=`` object."""
    vertices, faces = _tensors(bumpy)
    assert DEFAULT_VARIANT == "robust"
    robust = sl.saliency(vertices, faces, variant="robust", num_scales=5)
    assert torch.equal(sl.saliency(vertices, faces, num_scales=5), robust)
    assert torch.equal(sl.saliency(vertices, faces, params=sl.RobustParams(num_scales=5)), robust)
    paper = sl.saliency(vertices, faces, variant="paper", num_scales=5)
    assert torch.equal(sl.saliency(vertices, faces, params=sl.PaperParams(num_scales=5)), paper)

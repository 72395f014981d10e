"""Every public entry point runs under ``torch.inference_mode()`` and ``torch.no_grad()``.

PyTorch Lightning validates and tests under inference mode; 0.1.0 failed there on every CPU
entry point ("Inference tensors do not track version counter"). Each call must give the same
numbers as outside the mode, and outputs made inside must be usable afterwards.
"""

from __future__ import annotations

import pytest
import torch
from reference import noisy_sphere

import stochlap_torch as sl
from stochlap_torch.baselines import (
    heat_kernel_signature,
    laplacian_saliency,
    lee_saliency,
    spectral_reconstruction,
)

MODES = {"inference_mode": torch.inference_mode, "no_grad": torch.no_grad}


def _mesh():
    vertices, faces = noisy_sphere().tensors()
    return vertices, faces


def _batch():
    a, b = noisy_sphere(seed=1), noisy_sphere(seed=2)
    packed = sl.MeshBatch.from_meshes([sl.Mesh(*a.tensors()), sl.Mesh(*b.tensors())])
    return packed.vertices, packed.faces, packed.batch


CALLS = {
    "saliency robust": lambda v, f: sl.saliency(v, f),
    "saliency paper": lambda v, f: sl.saliency(v, f, variant="paper"),
    "saliency normal_displacement": lambda v, f: sl.saliency(v, f, variant="normal_displacement"),
    "multiscale_representation": lambda v, f: sl.multiscale_representation(v, f, 4).positions,
    "return_operators": lambda v, f: (
        sl.multiscale_representation(v, f, 3, return_operators=True).operators[-1].values()
    ),
    "torch backend": lambda v, f: sl.multiscale_representation(v, f, 3, backend="torch").positions,
    "features robust": lambda v, f: sl.multiscale_features(v, f),
    "features paper": lambda v, f: sl.multiscale_features(v, f, variant="paper"),
    "differentiable_multiscale": lambda v, f: sl.differentiable_multiscale(v, f, 3).positions,
    "interest_points": lambda v, f: sl.interest_points(sl.saliency(v, f), v, f, top_k=5),
    "StochasticLaplacian": lambda v, f: sl.StochasticLaplacian(3)(v, f).positions,
    "RobustMultiscale": lambda v, f: sl.RobustMultiscale()(v, f).dn,
    "MultiscaleSaliency": lambda v, f: sl.MultiscaleSaliency()(v, f),
    "MultiscaleFeatures": lambda v, f: sl.MultiscaleFeatures()(v, f),
    "InterestPointHead": lambda v, f: sl.InterestPointHead(top_k=5)(sl.saliency(v, f), v, f),
    "heat_kernel_signature": lambda v, f: heat_kernel_signature(v, f, 16),
    "spectral_reconstruction": lambda v, f: spectral_reconstruction(v, f, [8]),
    "lee_saliency": lambda v, f: lee_saliency(v, f),
    "laplacian_saliency": lambda v, f: laplacian_saliency(v, f),
}


def _as_tensor(result) -> torch.Tensor:
    return result if isinstance(result, torch.Tensor) else torch.as_tensor(result)


@pytest.mark.parametrize("name", sorted(CALLS))
@pytest.mark.parametrize("mode", sorted(MODES))
def test_entry_point_under_mode_matches_grad_mode(name, mode):
    vertices, faces = _mesh()
    expected = _as_tensor(CALLS[name](vertices, faces)).detach()
    with MODES[mode]():
        inside_vertices = vertices.clone()  # an inference tensor under inference_mode
        result = _as_tensor(CALLS[name](inside_vertices, faces))
    torch.testing.assert_close(result, expected, atol=1e-10, rtol=1e-10)
    assert bool(torch.isfinite(result.double()).all())


@pytest.mark.parametrize("mode", sorted(MODES))
def test_batches_and_the_pyg_transform_under_mode(mode):
    vertices, faces, batch = _batch()
    expected = sl.saliency(vertices, faces, batch=batch)
    with MODES[mode]():
        torch.testing.assert_close(sl.saliency(vertices, faces, batch=batch), expected)
        features = sl.MultiscaleFeatures()(vertices, faces, batch)
    assert features.shape[0] == vertices.shape[0]
    pyg = pytest.importorskip("torch_geometric.data", reason="the transform needs torch-geometric")
    data = pyg.Data(pos=vertices, face=faces.T.contiguous())
    with MODES[mode]():
        out = sl.StochasticFeatures()(data)
    assert out.x.shape[0] == vertices.shape[0]


def test_a_structure_built_under_inference_mode_serves_gradients():
    """Built (or loaded) under ``torch.inference_mode()`` and then used in a training step:
    the structure holds no inference tensor ("Inference tensors cannot be saved for backward"
    before), and its features are the same as in the mode."""
    mesh = sl.load_mesh(sl.bundled_mesh_path())
    with torch.inference_mode():
        structure = sl.robust_structure(mesh.vertices, mesh.faces)
        expected = structure.features(mesh.vertices)
        loaded = sl.RobustStructure.from_state_dict(structure.state_dict())
    for reused in (structure, loaded):
        vertices = mesh.vertices.clone().requires_grad_(True)
        features = sl.multiscale_features(vertices, mesh.faces, structure=reused)
        features.square().sum().backward()
        assert torch.equal(features.detach(), expected)
        assert torch.isfinite(vertices.grad).all() and vertices.grad.abs().sum() > 0

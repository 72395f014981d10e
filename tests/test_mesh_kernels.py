"""The numba construction of ``Lhat`` and ``alpha`` equals the torch construction, and the
edges read from either ``Lhat`` are the mesh's unique edges."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from reference import SmallMesh, icosphere, two_components

import stochlap_torch as sl
from stochlap_torch import _kernels as mesh_kernels
from stochlap_torch.mesh import unique_edges
from stochlap_torch.operators import (
    MeshOperators,
    abs_laplacian,
    alpha_from_edges,
    operators_of_valid_mesh,
)

pytestmark = pytest.mark.skipif(not mesh_kernels.numba_available(), reason="numba is not installed")

TOLERANCE = {torch.float64: 1e-13, torch.float32: 1e-6}


def _by_torch(vertices: torch.Tensor, faces: torch.Tensor) -> MeshOperators:
    edges = unique_edges(faces, vertices.shape[0])
    reference = MeshOperators(abs_laplacian(vertices, edges), alpha_from_edges(vertices, edges))
    assert torch.equal(reference.edges, edges)
    return reference


def _assert_same(kernel: MeshOperators, reference: MeshOperators, dtype: torch.dtype) -> None:
    assert torch.equal(kernel.edges, reference.edges)
    assert torch.equal(kernel.lhat.crow, reference.lhat.crow)
    assert torch.equal(kernel.lhat.col, reference.lhat.col)
    assert kernel.lhat.val.dtype == kernel.alpha.dtype == dtype
    rtol = TOLERANCE[dtype]
    torch.testing.assert_close(kernel.lhat.val, reference.lhat.val, rtol=rtol, atol=0)
    torch.testing.assert_close(kernel.alpha, reference.alpha, rtol=rtol, atol=0)


def _non_manifold() -> SmallMesh:
    """Three triangles on one edge (0, 1), a fourth vertex unused, one isolated triangle."""
    vertices = np.array(
        [
            [0, 0, 0],
            [1, 0, 0],
            [0.5, 1, 0],
            [0.5, -1, 0.2],
            [0.5, 0.1, 1],
            [9, 9, 9],
            [3, 0, 0],
            [4, 0.1, 0],
            [3.5, 1, 0.3],
        ],
        dtype=np.float64,
    )
    faces = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4], [6, 7, 8]], dtype=np.int64)
    return SmallMesh("non_manifold", vertices, faces)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_kernel_operators_equal_the_torch_construction(small_mesh, dtype) -> None:
    """Boundaries, several components and unreferenced vertices included."""
    vertices, faces = small_mesh.tensors(dtype)
    _assert_same(operators_of_valid_mesh(vertices, faces), _by_torch(vertices, faces), dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_non_manifold_edges_and_isolated_vertices(dtype) -> None:
    vertices, faces = _non_manifold().tensors(dtype)
    ops = operators_of_valid_mesh(vertices, faces)
    _assert_same(ops, _by_torch(vertices, faces), dtype)
    dense = ops.lhat.to_dense()
    assert dense[5, 5] == 1 and dense[5].count_nonzero() == 1  # no edges: e_5
    assert ops.alpha[5] == 1
    assert dense[0].count_nonzero() == 5  # itself, 1, 2, 3, 4: the shared edge once


def test_real_meshes_with_defects(meshes_dir) -> None:
    """squirrel (non-manifold edges) and bunny (boundary, unreferenced vertices)."""
    for name in ("squirrel.off", "bunny.obj"):
        mesh = sl.load_mesh(meshes_dir / name)
        _assert_same(
            operators_of_valid_mesh(mesh.vertices, mesh.faces),
            _by_torch(mesh.vertices, mesh.faces),
            mesh.vertices.dtype,
        )


def test_zero_length_edge_is_named() -> None:
    """The kernel reports the infinite weight; the error names the edge, as the torch path."""
    sphere = icosphere(1)
    vertices = sphere.vertices.copy()
    a, b = sphere.faces[0, :2]
    vertices[b] = vertices[a]
    with pytest.raises(sl.MeshError, match=f"{min(a, b)}.*{max(a, b)}"):
        operators_of_valid_mesh(torch.from_numpy(vertices), torch.from_numpy(sphere.faces))


def test_gradients_and_batches_take_the_torch_construction() -> None:
    """The kernel has no autograd and no per-mesh ``c`` of Eq. 9: vertices that need gradients
    and packed batches get the torch operators."""
    vertices, faces = icosphere(1).tensors(torch.float64)
    vertices.requires_grad_(True)
    ops = operators_of_valid_mesh(vertices, faces)
    assert ops.lhat.val.requires_grad
    ops.lhat.val.sum().backward()
    assert vertices.grad is not None and torch.isfinite(vertices.grad).all()

    vertices, faces = two_components().tensors(torch.float64)
    first_vertices, first_faces = 42, 80  # icosphere(1), then a shifted icosphere(0)
    batch = (torch.arange(vertices.shape[0]) >= first_vertices).long()
    packed = operators_of_valid_mesh(vertices, faces, batch)
    alone = [
        operators_of_valid_mesh(vertices[:first_vertices], faces[:first_faces]),
        operators_of_valid_mesh(vertices[first_vertices:], faces[first_faces:] - first_vertices),
    ]
    torch.testing.assert_close(packed.alpha, torch.cat([ops.alpha for ops in alone]))

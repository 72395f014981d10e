"""Packed batches: every per-vertex result equals that of separate runs on each mesh."""

from __future__ import annotations

import pytest
import torch
from reference import SMALL_MESH_BUILDERS, SmallMesh

import stochlap_torch as sl
from stochlap_torch.sparse import CSR


def _meshes(dtype: torch.dtype = torch.float64) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Three meshes of different sizes, one with an unreferenced vertex, scaled differently.

    The vertices are jittered so that no two saliency values tie: interest points of a batch
    and of separate runs may otherwise break exact ties differently under rounding.
    """
    names = ("icosphere2", "open_grid", "unreferenced_vertex")
    generator = torch.Generator().manual_seed(0)
    chosen: list[SmallMesh] = [SMALL_MESH_BUILDERS[name]() for name in names]
    pairs = []
    for scale, mesh in zip((1.0, 7.5, 0.01), chosen, strict=True):
        vertices, faces = mesh.tensors(torch.float64)
        jitter = 1e-2 * torch.rand(vertices.shape, generator=generator, dtype=torch.float64)
        pairs.append((((vertices + jitter) * scale).to(dtype), faces))
    return pairs


def test_pack_and_unbatch_round_trip() -> None:
    pairs = _meshes()
    packed = sl.MeshBatch.from_meshes(pairs)
    assert packed.num_meshes == 3
    assert packed.ptr.tolist()[-1] == sum(v.shape[0] for v, _ in pairs)
    for index, (vertices, faces) in enumerate(pairs):
        mesh = packed.mesh(index)
        assert torch.equal(mesh.vertices, vertices) and torch.equal(mesh.faces, faces)
    pieces = packed.unbatch(packed.vertices)
    assert [p.shape[0] for p in pieces] == [v.shape[0] for v, _ in pairs]


@pytest.mark.parametrize("backend", ["numba", "torch"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_batch_equals_separate_runs(backend: str, dtype: torch.dtype) -> None:
    pairs = _meshes(dtype)
    packed = sl.MeshBatch.from_meshes(pairs)
    layer = sl.StochasticLaplacian(num_scales=5, return_operators=True)
    together = sl.multiscale_representation(
        packed.vertices,
        packed.faces,
        5,
        batch=packed.batch,
        backend=backend,
        return_operators=True,
    )
    tolerance = 1e-12 if dtype == torch.float64 else 1e-5
    saliency = together.saliency()
    for index, (vertices, faces) in enumerate(pairs):
        alone = sl.multiscale_representation(
            vertices, faces, 5, backend=backend, return_operators=True
        )
        rows = slice(int(packed.ptr[index]), int(packed.ptr[index + 1]))
        for name in ("positions", "differences"):
            torch.testing.assert_close(
                getattr(together, name)[:, rows],
                getattr(alone, name),
                rtol=tolerance,
                atol=tolerance,
            )
        torch.testing.assert_close(saliency[rows], alone.saliency(), rtol=tolerance, atol=tolerance)
        for big, small in zip(together.operators, alone.operators, strict=True):
            block = CSR.from_sparse_csr(big).to_dense()[rows, rows]
            torch.testing.assert_close(block, small.to_dense(), rtol=tolerance, atol=tolerance)
    from_layer = layer(packed.vertices, packed.faces, packed.batch)
    torch.testing.assert_close(
        from_layer.positions, together.positions, rtol=tolerance, atol=tolerance
    )


def test_batch_operators_are_block_diagonal() -> None:
    packed = sl.MeshBatch.from_meshes(_meshes())
    rep = sl.multiscale_representation(
        packed.vertices, packed.faces, 6, batch=packed.batch, return_operators=True
    )
    for operator in rep.operators:
        matrix = CSR.from_sparse_csr(operator)
        rows = torch.repeat_interleave(torch.arange(matrix.num_rows), matrix.crow.diff())
        assert torch.equal(packed.batch[rows], packed.batch[matrix.col])


@pytest.mark.filterwarnings("ignore::stochlap_torch.interest.InterestPointWarning")
def test_batch_interest_points_equal_separate_runs() -> None:
    pairs = _meshes()
    packed = sl.MeshBatch.from_meshes(pairs)
    saliency = sl.MultiscaleSaliency(num_scales=5, variant="paper")(
        packed.vertices, packed.faces, packed.batch
    )
    head = sl.InterestPointHead(radius=0.2, top_k=4)
    together = head(saliency, packed.vertices, packed.faces, packed.batch)
    expected = []
    for index, (vertices, faces) in enumerate(pairs):
        alone = head(sl.saliency(vertices, faces, num_scales=5, variant="paper"), vertices, faces)
        expected.append(alone + int(packed.ptr[index]))
    assert together.tolist() == torch.cat(expected).tolist()


def test_batch_vector_is_checked() -> None:
    packed = sl.MeshBatch.from_meshes(_meshes())
    wrong = packed.batch.clone()
    wrong[0] = 1  # vertex 0 now belongs to mesh 1 while its faces are in mesh 0
    with pytest.raises(sl.MeshError, match="join vertices of different meshes"):
        sl.multiscale_representation(packed.vertices, packed.faces, 3, batch=wrong)
    with pytest.raises(sl.MeshError, match="shape"):
        sl.multiscale_representation(packed.vertices, packed.faces, 3, batch=packed.batch[:-1])
    with pytest.raises(sl.MeshError, match="empty batch"):
        sl.MeshBatch.from_meshes([])


def test_mesh_index_follows_python_conventions() -> None:
    """A negative index counts from the end; one out of range is an ``IndexError``."""
    pairs = _meshes()
    packed = sl.MeshBatch.from_meshes(pairs)
    for index in (-1, -3):
        vertices, faces = pairs[index]
        mesh = packed.mesh(index)
        assert torch.equal(mesh.vertices, vertices) and torch.equal(mesh.faces, faces)
    for index in (3, -4):
        with pytest.raises(IndexError, match="out of range"):
            packed.mesh(index)

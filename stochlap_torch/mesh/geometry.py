"""Geometry and connectivity of a mesh: edges, lengths, normals, valence, orientation, areas,
components.

Every function takes ``(V, 3)`` float vertices and ``(F, 3)`` int64 faces (or the unique edges
derived from them), works on any device and dtype, and is differentiable where that makes
sense. These are the only definitions of these quantities in the package.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .._common.tensors import safe_norm, unique_with_inverse

__all__ = [
    "connected_components",
    "edge_lengths",
    "extent_scale",
    "face_areas",
    "face_corners",
    "face_normals",
    "mean_edge_length",
    "mesh_extent",
    "outward_sign",
    "unique_edges",
    "vertex_degree",
    "vertex_mean_edge_length",
    "vertex_normals",
    "vertex_valence",
]


def unique_edges(faces: Tensor, num_vertices: int | None = None) -> Tensor:
    """Unique undirected edges of a triangle mesh.

    Args:
        faces: ``(F, 3)`` int64.
        num_vertices: ``V``; defaults to ``faces.max() + 1``.

    Returns:
        ``(E, 2)`` int64, ``edges[:, 0] < edges[:, 1]``, sorted lexicographically.
    """
    if num_vertices is None:
        num_vertices = int(faces.max()) + 1
    corners = torch.stack([faces, faces.roll(-1, dims=1)], dim=2).reshape(-1, 2)
    low, high = corners.min(dim=1).values, corners.max(dim=1).values
    keys, _ = unique_with_inverse(low * num_vertices + high)
    return torch.stack([keys // num_vertices, keys % num_vertices], dim=1)


def connected_components(num_vertices: int, edges: np.ndarray) -> np.ndarray:
    """``(V,)`` int64 component label of every vertex (labels ``0..C-1``) from ``(E, 2)``
    integer edges; a vertex without edges is a component of its own."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ones = np.ones(edges.shape[0], dtype=np.int8)
    graph = coo_matrix((ones, (edges[:, 0], edges[:, 1])), shape=(num_vertices, num_vertices))
    return scipy_components(graph, directed=False)[1].astype(np.int64)


def edge_lengths(vertices: Tensor, edges: Tensor) -> Tensor:
    """``(E,)`` Euclidean lengths of ``(E, 2)`` edges."""
    return (vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=1)


def vertex_degree(edges: Tensor, num_vertices: int, dtype: torch.dtype) -> Tensor:
    """``(V,)`` number of edges at every vertex, in ``dtype`` (0 for a vertex without edges)."""
    count = torch.zeros(num_vertices, dtype=dtype, device=edges.device)
    ones = torch.ones(edges.shape[0], dtype=dtype, device=edges.device)
    return count.index_add_(0, edges[:, 0], ones).index_add_(0, edges[:, 1], ones)


def vertex_valence(faces: Tensor, num_vertices: int) -> Tensor:
    """``(V,)`` int64 number of distinct 1-ring neighbours of every vertex (0 if unreferenced)."""
    edges = unique_edges(faces, num_vertices)
    return torch.bincount(edges.reshape(-1), minlength=num_vertices)


def mean_edge_length(
    vertices: Tensor, edges: Tensor, batch: Tensor | None = None, lengths: Tensor | None = None
) -> Tensor:
    """Mean length of the unique edges of each mesh: ``(1,)``, or ``(B,)`` for a packed batch.

    Args:
        vertices: ``(V, 3)`` float.
        edges: ``(E, 2)`` int64 unique undirected edges.
        batch: optional ``(V,)`` int64 mesh index of every vertex; a mesh without edges gets 0.
        lengths: the ``(E,)`` :func:`edge_lengths`, if already computed.
    """
    if lengths is None:
        lengths = edge_lengths(vertices, edges)
    if batch is None:
        return lengths.mean().reshape(1)
    edge_mesh = batch[edges[:, 0]]
    num_meshes = int(batch.max()) + 1
    sums = lengths.new_zeros(num_meshes).index_add_(0, edge_mesh, lengths)
    counts = lengths.new_zeros(num_meshes).index_add_(0, edge_mesh, torch.ones_like(lengths))
    return sums / counts.clamp_min(1)


def vertex_mean_edge_length(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V,)`` mean length of the unique edges at every vertex; 0 for a vertex without edges."""
    num_vertices = vertices.shape[0]
    edges = unique_edges(faces, num_vertices)
    lengths = edge_lengths(vertices, edges)
    total = vertices.new_zeros(num_vertices)
    total.index_add_(0, edges[:, 0], lengths).index_add_(0, edges[:, 1], lengths)
    count = torch.bincount(edges.reshape(-1), minlength=num_vertices).to(vertices.dtype)
    return torch.where(count > 0, total / count.clamp_min(1.0), torch.zeros_like(total))


def face_corners(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3, C)`` the corners of every face: ``vertices[faces]``, gathered by
    ``index_select`` at half the cost of that indexing on the CPU."""
    return vertices.index_select(0, faces.reshape(-1)).reshape(-1, 3, vertices.shape[1])


def face_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3)`` face normals scaled by twice the face area (the raw cross products)."""
    corners = face_corners(vertices, faces)
    return torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def face_areas(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F,)`` triangle areas."""
    return 0.5 * face_normals(vertices, faces).norm(dim=1)


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V, 3)`` unit vertex normals: the area-weighted sum of the incident face normals (it
    follows the faces' orientation); zero at a vertex no face uses (or whose face normals
    cancel), with a zero (not NaN) gradient there."""
    # |cross| is twice the face area: summing the raw cross products weights by area.
    cross = face_normals(vertices, faces)
    summed = vertices.new_zeros(vertices.shape).index_add(
        0, faces.reshape(-1), cross.repeat_interleave(3, dim=0)
    )
    length = safe_norm(summed, dim=1).unsqueeze(1)
    return torch.where(
        length > 0,
        summed / length.clamp_min(torch.finfo(length.dtype).tiny),
        torch.zeros_like(summed),
    )


def outward_sign(vertices: Tensor, faces: Tensor, batch: Tensor | None = None) -> Tensor:
    """``(V,)`` ``+1.0`` where the faces of the vertex's mesh are oriented outwards, ``-1.0``
    where inwards, in the dtype of ``vertices``; ``batch``: optional ``(V,)`` int64 mesh index.

    The test is the sign of ``sum_f (a - o) . ((b - o) x (c - o))`` over the faces ``(a, b, c)``
    of a mesh, ``o`` its centroid (six times the enclosed volume for a closed mesh).
    """
    batch, num_meshes = _labels(vertices, batch)
    count = torch.bincount(batch, minlength=num_meshes).clamp_min(1).to(vertices.dtype)
    centre = vertices.new_zeros(num_meshes, 3).index_add_(0, batch, vertices) / count[:, None]
    corners = face_corners(vertices, faces) - centre[batch[faces[:, 0]]].unsqueeze(1)
    triple = (corners[:, 0] * torch.linalg.cross(corners[:, 1], corners[:, 2])).sum(dim=1)
    volume = vertices.new_zeros(num_meshes).index_add_(0, batch[faces[:, 0]], triple)
    return torch.where(volume[batch] < 0, -1.0, 1.0).to(vertices.dtype)


def mesh_extent(vertices: Tensor, batch: Tensor | None = None) -> Tensor:
    """Diagonal of the axis-aligned bounding box of each mesh: ``(1,)`` or ``(B,)``."""
    batch, num_meshes = _labels(vertices, batch)
    index = batch.unsqueeze(1).expand(-1, 3)
    high, low = (
        vertices.new_full((num_meshes, 3), fill).scatter_reduce(0, index, vertices, reduce=how)
        for fill, how in ((-torch.inf, "amax"), (torch.inf, "amin"))
    )
    return safe_norm(high - low, dim=1)


def _labels(vertices: Tensor, batch: Tensor | None) -> tuple[Tensor, int]:
    """``(V,)`` int64 mesh labels (``batch``, or all zero) and the number of meshes."""
    if batch is None:
        batch = torch.zeros(vertices.shape[0], dtype=torch.int64, device=vertices.device)
    return batch, int(batch.max()) + 1 if batch.numel() else 1


def extent_scale(vertices: Tensor) -> float:
    """A power of two ``s`` that brings the bounding box of ``vertices`` into ``[1, 2)``, or
    ``1.0`` when its size is already safe for the dtype.

    The method is scale invariant, and scaling by a power of two is exact in floating point,
    so computing on ``s * vertices`` gives the same operators, bit for bit, with no overflow
    of squared edge lengths and no underflow of tiny ones. For subnormal coordinates ``s`` is
    the largest power of two the dtype holds (still exact: a subnormal times a power of two
    that keeps it finite loses no bits).
    """
    if vertices.numel() == 0:
        return 1.0
    with torch.no_grad():
        extent = float((vertices.amax(dim=0) - vertices.amin(dim=0)).max())
    # Squares of lengths up to 2**safe and their reciprocals stay finite and normal.
    largest = torch.finfo(vertices.dtype).max
    safe = int(math.log2(largest)) // 4
    if not math.isfinite(extent) or extent == 0.0 or -safe <= math.log2(extent) <= safe:
        return 1.0
    return 2.0 ** min(-math.floor(math.log2(extent)), math.frexp(largest)[1] - 1)

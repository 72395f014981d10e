"""From a mesh to the operators of the paper's method (Sec. 3.2 and 3.3): ``Lhat = |D - W|``
with ``W(i, j) = 1 / |Pi - Pj|^2`` (Eqs. 3-5) and ``alpha`` (Eq. 9).

A vertex with no edges (unreferenced by the faces) gets ``Lhat(i, i) = 1``: its row of every
``F^(k)`` is the unit vector ``e_i``, so it keeps its position and influences no other vertex.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from .. import _kernels
from ..mesh import as_mesh_tensors, unique_edges
from ..mesh.geometry import edge_lengths, mean_edge_length, vertex_degree
from ..mesh.validation import zero_length_error
from ..sparse import CSR, normalize_rows, symmetric_csr

__all__ = [
    "MeshOperators",
    "abs_laplacian",
    "alpha_from_edges",
    "mesh_operators",
    "operators_of_valid_mesh",
    "scale_invariance",
    "stochastic_laplacian",
]


@dataclass(frozen=True)
class MeshOperators:
    """Everything the diffusion steps need from the mesh; every construction returns one.

    Attributes:
        lhat: ``Lhat`` as a ``(V, V)`` :class:`~stochlap_torch.sparse.CSR` with non-negative
            values, every edge of the mesh stored (whatever its weight) and every diagonal
            entry; ``F^(1)`` is ``Lhat`` normalised by rows.
        alpha: ``(V,)`` the factor every column of a step's product is multiplied by
            (Eq. 9 for the paper's operators).
    """

    lhat: CSR
    alpha: Tensor

    @cached_property
    def edges(self) -> Tensor:
        """``(E, 2)`` int64 unique undirected edges ``i < j``, lexicographic: the entries of
        ``Lhat`` above its diagonal, read from it on first access (the steps never need them)."""
        crow, col = self.lhat.crow, self.lhat.col
        rows = torch.arange(self.num_vertices, device=col.device).repeat_interleave(crow.diff())
        upper = col > rows
        return torch.stack([rows[upper], col[upper]], dim=1)

    @property
    def num_vertices(self) -> int:
        return self.lhat.num_rows

    def stochastic_laplacian(self) -> CSR:
        """``F^(1)``: ``Lhat`` normalised by rows."""
        return normalize_rows(self.lhat)


def abs_laplacian(vertices: Tensor, edges: Tensor) -> CSR:
    """``Lhat = |D - W|``, ``W(i, j) = 1 / |Pi - Pj|^2`` on the ``(E, 2)`` int64 unique
    undirected ``edges`` of ``(V, 3)`` float ``vertices``: a ``(V, V)`` CSR in their dtype,
    ``W(i, j)`` off the diagonal, ``D(i, i) = sum_j W(i, j)`` on it (``1`` without edges).

    Raises:
        MeshError: an edge has zero length (its weight is not finite in this dtype).
    """
    weights = 1.0 / (vertices[edges[:, 0]] - vertices[edges[:, 1]]).square().sum(dim=1)
    infinite = ~torch.isfinite(weights)
    if bool(infinite.any()):
        raise zero_length_error(edges[infinite])
    degree = vertices.new_zeros(vertices.shape[0])
    degree.index_add_(0, edges[:, 0], weights).index_add_(0, edges[:, 1], weights)
    degree = torch.where(degree > 0, degree, torch.ones_like(degree))
    return symmetric_csr(edges, weights, degree)


def alpha_from_edges(vertices: Tensor, edges: Tensor, batch: Tensor | None = None) -> Tensor:
    """``(V,)`` ``alpha(i) = c n_i / sum_{j in N(i)} |Pi - Pj| + 1`` (Eq. 9) of ``(V, 3)``
    float ``vertices`` and their ``(E, 2)`` int64 unique undirected ``edges``: ``c`` the mean
    edge length, per mesh with the optional ``(V,)`` int64 ``batch`` of a packed batch
    (``None``: one mesh)."""
    lengths = edge_lengths(vertices, edges)
    count = vertex_degree(edges, vertices.shape[0], vertices.dtype)
    total = vertices.new_zeros(vertices.shape[0])
    total.index_add_(0, edges[:, 0], lengths).index_add_(0, edges[:, 1], lengths)
    mean_length = mean_edge_length(vertices, edges, batch, lengths)
    if batch is not None:
        mean_length = mean_length[batch]
    has_edges = count > 0
    ratio = mean_length * count / torch.where(has_edges, total, torch.ones_like(total))
    return torch.where(has_edges, ratio + 1.0, torch.ones_like(ratio))


def mesh_operators(vertices, faces, batch: Tensor | None = None) -> MeshOperators:
    """``Lhat`` and ``alpha`` of a mesh, validated here: ``(V, 3)`` float ``vertices``
    (array-likes read as float64), ``(F, 3)`` integer ``faces`` and the optional ``(V,)`` int64
    ``batch``, the mesh index of every vertex of a packed :class:`~stochlap_torch.mesh.MeshBatch`
    (``None``: one mesh).

    Raises:
        MeshError: for any input :func:`~stochlap_torch.mesh.validate_mesh` rejects.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    return operators_of_valid_mesh(vertices, faces, batch)


def operators_of_valid_mesh(
    vertices: Tensor, faces: Tensor, batch: Tensor | None = None
) -> MeshOperators:
    """:func:`mesh_operators` of tensors that passed :func:`~stochlap_torch.mesh.validate_mesh`
    (zero-length edges still raise here; ``batch`` as there, ``None``: one mesh); single CPU
    meshes without gradient by the numba kernel, with the same result."""
    if (
        batch is None
        and vertices.device.type == "cpu"
        and _kernels.numba_available()
        and vertices.dtype in (torch.float32, torch.float64)
        and vertices.shape[0] < 2**31
        and not (vertices.requires_grad and torch.is_grad_enabled())
    ):
        vertices = vertices.detach()
        *lhat, alpha, finite = _kernels.lhat_parts(
            np.ascontiguousarray(vertices.numpy()), np.ascontiguousarray(faces.numpy())
        )
        if not finite:  # raises, naming the zero-length edges
            abs_laplacian(vertices, unique_edges(faces, vertices.shape[0]))
        lhat = CSR(*map(torch.from_numpy, lhat), vertices.shape[0])
        return MeshOperators(lhat, torch.from_numpy(alpha))
    edges = unique_edges(faces, vertices.shape[0])
    alpha = alpha_from_edges(vertices, edges, batch)
    return MeshOperators(abs_laplacian(vertices, edges), alpha)


def scale_invariance(vertices, faces) -> Tensor:
    """``(V,)`` scale invariance function ``alpha`` of Eq. 9 for a mesh (validated)."""
    return mesh_operators(vertices, faces).alpha


def stochastic_laplacian(vertices, faces) -> Tensor:
    """The stochastic mesh Laplacian ``[|L|]_r`` of Eq. 5 as a ``(V, V)`` ``torch.sparse_csr``."""
    return mesh_operators(vertices, faces).stochastic_laplacian().to_sparse_csr()

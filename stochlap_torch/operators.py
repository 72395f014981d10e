"""From a mesh to the operators of the method (paper Sec. 3.2 and 3.3).

* :func:`unique_edges`: the undirected edges of the faces, each once.
* :func:`abs_laplacian`: ``Lhat = |D - W|`` with ``W(i, j) = 1 / |Pi - Pj|^2`` (Eqs. 3-5),
  from the unique edges.
* :func:`stochastic_laplacian`: ``Lhat`` with each row divided by its sum, ``F^(1)``.
* :func:`scale_invariance`: ``alpha(i) = c n_i / sum_j |Pi - Pj| + 1`` (Eq. 9), from a mesh;
  :func:`alpha_from_edges` from the unique edges.

A vertex with no edges (unreferenced by the faces) gets ``Lhat(i, i) = 1``: its row of every
``F^(k)`` is the unit vector ``e_i``, so it keeps its position and influences no other vertex.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from . import mesh_kernels
from .mesh import as_mesh_tensors, zero_length_error
from .sparse_ops import CSR, normalize_rows, unique_with_inverse

__all__ = [
    "LOCALITY_MIN_VERTICES",
    "MeshOperators",
    "abs_laplacian",
    "alpha_from_edges",
    "locality_order",
    "mesh_operators",
    "operators_of_valid_mesh",
    "scale_invariance",
    "stochastic_laplacian",
    "unique_edges",
]


#: Meshes at least this large are renumbered along a space-filling curve before the steps
#: (the kernel computes four consecutive rows together, which pays when they are neighbours:
#: 10k-vertex meshes in file order run 1.5-1.7 times faster renumbered).
LOCALITY_MIN_VERTICES = 4096


#: ``(shift, mask)`` rounds that spread the low 21 bits of an int64 two bits apart.
_SPREAD_ROUNDS = (
    (32, 0x1F00000000FFFF),
    (16, 0x1F0000FF0000FF),
    (8, 0x100F00F00F00F00F),
    (4, 0x10C30C30C30C30C3),
    (2, 0x1249249249249249),
)


def _spread_bits_(x: Tensor, scratch: Tensor) -> Tensor:
    """In place: insert two zero bits between the low 21 bits of each int64 of ``x`` (for 3D
    Morton codes); ``scratch`` is an int64 tensor of the same shape."""
    x.bitwise_and_(0x1FFFFF)
    for shift, mask in _SPREAD_ROUNDS:
        torch.bitwise_left_shift(x, shift, out=scratch)
        x.bitwise_or_(scratch).bitwise_and_(mask)
    return x


def locality_order(vertices: Tensor) -> Tensor:
    """``(V,)`` int64 vertex order along a Morton (Z-order) curve of the positions.

    Renumbering a mesh in this order puts the neighbours of a vertex close to it in memory,
    which speeds up the row-by-row products severalfold on meshes whose file order is poor
    (for example after subdivision). Ties keep the file order.

    The codes are built in place in three ``(V,)`` buffers. A temporary per operation made
    about 40 fresh ``(V,)`` int64 arrays: at 10.5M vertices, each a fresh mapping of 84 MB,
    4.9 GB of page faults in all.
    """
    low = vertices.min(dim=0).values
    extent = (vertices.max(dim=0).values - low).max().clamp_min(torch.finfo(vertices.dtype).tiny)
    cells = (vertices - low).div_(extent).mul_(2**21 - 1)  # (V, 3) float in [0, 2**21 - 1]
    code = torch.zeros(vertices.shape[0], dtype=torch.int64, device=vertices.device)
    part, scratch = torch.empty_like(code), torch.empty_like(code)
    for axis in range(3):
        part.copy_(cells[:, axis])  # truncates, as .to(torch.int64) does
        code.bitwise_or_(_spread_bits_(part, scratch).bitwise_left_shift_(axis))
    del cells, part, scratch
    return torch.argsort(code, stable=True)


@dataclass(frozen=True)
class MeshOperators:
    """Everything the diffusion steps need from the mesh.

    Attributes:
        lhat: ``Lhat = |L|`` as a ``(V, V)`` :class:`~stochlap_torch.sparse_ops.CSR`, every
            edge of the mesh stored (whatever its weight) and every diagonal entry.
        alpha: ``(V,)`` scale invariance function of Eq. 9.
    """

    lhat: CSR
    alpha: Tensor

    @cached_property
    def edges(self) -> Tensor:
        """``(E, 2)`` int64 unique undirected edges ``i < j``, lexicographic: the entries of
        ``Lhat`` above its diagonal (read from it on first access; the steps never need
        them, and at 10M vertices they are half a gigabyte)."""
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


def _edge_lengths(vertices: Tensor, edges: Tensor) -> Tensor:
    """``(E,)`` Euclidean lengths of ``(E, 2)`` edges."""
    return (vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=1)


def _symmetric_csr(edges: Tensor, edge_values: Tensor, diagonal: Tensor) -> CSR:
    """``(V, V)`` CSR with ``edge_values`` at ``(i, j)`` and ``(j, i)`` and ``diagonal`` on it."""
    num_vertices = diagonal.shape[0]
    arange = torch.arange(num_vertices, device=edges.device)
    rows = torch.cat([edges[:, 0], edges[:, 1], arange])
    cols = torch.cat([edges[:, 1], edges[:, 0], arange])
    vals = torch.cat([edge_values, edge_values, diagonal])
    order = torch.argsort(rows * num_vertices + cols)
    rows, cols, vals = rows[order], cols[order], vals[order]
    crow = torch.zeros(num_vertices + 1, dtype=torch.int64, device=edges.device)
    torch.cumsum(torch.bincount(rows, minlength=num_vertices), dim=0, out=crow[1:])
    return CSR(crow, cols, vals, num_vertices)


def abs_laplacian(vertices: Tensor, edges: Tensor) -> CSR:
    """``Lhat = |D - W|``, ``W(i, j) = 1 / |Pi - Pj|^2`` on edges.

    Args:
        vertices: ``(V, 3)`` float.
        edges: ``(E, 2)`` int64 unique undirected edges.

    Returns:
        ``(V, V)`` CSR in the dtype of ``vertices``: ``W(i, j)`` off the diagonal,
        ``D(i, i) = sum_j W(i, j)`` on it (``1`` for a vertex with no edges).

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
    return _symmetric_csr(edges, weights, degree)


def alpha_from_edges(vertices: Tensor, edges: Tensor, batch: Tensor | None = None) -> Tensor:
    """``alpha(i) = c n_i / sum_{j in N(i)} |Pi - Pj| + 1`` (Eq. 9).

    Args:
        vertices: ``(V, 3)`` float.
        edges: ``(E, 2)`` int64 unique undirected edges.
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch; ``c`` is
            then taken per mesh, so each mesh gets the ``alpha`` it would get alone.

    Returns:
        ``(V,)`` float, ``> 1`` for every vertex with edges; ``1`` for a vertex without.
        ``c`` is the mean length of the unique edges (of the vertex's mesh).
    """
    lengths = _edge_lengths(vertices, edges)
    num_vertices = vertices.shape[0]
    count = vertices.new_zeros(num_vertices)
    total = vertices.new_zeros(num_vertices)
    ones = torch.ones_like(lengths)
    count.index_add_(0, edges[:, 0], ones).index_add_(0, edges[:, 1], ones)
    total.index_add_(0, edges[:, 0], lengths).index_add_(0, edges[:, 1], lengths)
    if batch is None:
        mean_length = lengths.mean()
    else:
        edge_mesh = batch[edges[:, 0]]
        num_meshes = int(batch.max()) + 1
        sums = lengths.new_zeros(num_meshes).index_add_(0, edge_mesh, lengths)
        counts = lengths.new_zeros(num_meshes).index_add_(0, edge_mesh, torch.ones_like(lengths))
        mean_length = (sums / counts.clamp_min(1))[batch]
    has_edges = count > 0
    ratio = mean_length * count / torch.where(has_edges, total, torch.ones_like(total))
    return torch.where(has_edges, ratio + 1.0, torch.ones_like(ratio))


def mesh_operators(vertices, faces, batch: Tensor | None = None) -> MeshOperators:
    """Validate a mesh and build ``Lhat``, ``alpha`` and the edge list.

    Args:
        vertices: ``(V, 3)`` float tensor (or array-like, read as float64).
        faces: ``(F, 3)`` integer tensor or array-like.
        batch: optional ``(V,)`` int64 mesh index of every vertex when ``vertices`` and
            ``faces`` pack several meshes (see :class:`~stochlap_torch.batch.MeshBatch`).

    Raises:
        MeshError: for any input :func:`~stochlap_torch.mesh.validate_mesh` rejects.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    return operators_of_valid_mesh(vertices, faces, batch)


def operators_of_valid_mesh(
    vertices: Tensor, faces: Tensor, batch: Tensor | None = None
) -> MeshOperators:
    """:func:`mesh_operators` for ``(V, 3)`` float and ``(F, 3)`` int64 tensors that have
    already passed :func:`~stochlap_torch.mesh.validate_mesh`, with or without its edge
    length check (zero-length edges still raise here, in :func:`abs_laplacian`).

    Single meshes on the CPU that need no gradient are built by the numba kernel of
    :mod:`.mesh_kernels`; the torch construction below gives the same operators everywhere
    else."""
    if (
        batch is None and vertices.device.type == "cpu" and mesh_kernels.available()
        and vertices.dtype in (torch.float32, torch.float64) and vertices.shape[0] < 2**31
        and not (vertices.requires_grad and torch.is_grad_enabled())
    ):  # fmt: skip
        return _operators_by_kernel(vertices.detach(), faces)
    edges = unique_edges(faces, vertices.shape[0])
    alpha = alpha_from_edges(vertices, edges, batch)
    return MeshOperators(abs_laplacian(vertices, edges), alpha)


def _operators_by_kernel(vertices: Tensor, faces: Tensor) -> MeshOperators:
    """:func:`operators_of_valid_mesh` by :func:`.mesh_kernels.lhat_parts` (CPU, no grad)."""
    parts = mesh_kernels.lhat_parts(
        np.ascontiguousarray(vertices.numpy()), np.ascontiguousarray(faces.numpy())
    )
    if not parts.finite:  # raises, naming the zero-length edges
        abs_laplacian(vertices, unique_edges(faces, vertices.shape[0]))
    crow, col, val = (torch.from_numpy(a) for a in (parts.crow, parts.col, parts.val))
    lhat = CSR(crow, col, val, vertices.shape[0])
    return MeshOperators(lhat, torch.from_numpy(parts.alpha))


def scale_invariance(vertices, faces) -> Tensor:
    """``(V,)`` scale invariance function ``alpha`` of Eq. 9 for a mesh (validated)."""
    return mesh_operators(vertices, faces).alpha


def stochastic_laplacian(vertices, faces) -> Tensor:
    """The stochastic mesh Laplacian ``[|L|]_r`` of Eq. 5 as a ``(V, V)`` ``torch.sparse_csr``."""
    return mesh_operators(vertices, faces).stochastic_laplacian().to_sparse_csr()

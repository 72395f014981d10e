"""The uniform, cotangent and intrinsic Delaunay mesh Laplacians, with lumped mass matrices
(paper Fig. 11).

Both Laplacians are ``L = D - W`` on the unique undirected edges of the faces, with
``D(i, i) = sum_j W(i, j)``; ``L`` is symmetric and positive semi-definite (for the cotangent
Laplacian when no edge weight is negative), so ``L 1 = 0``.

* uniform (Taubin 1995; paper ref. [34]): ``W(i, j) = 1`` on every edge. Its mass matrix is the
  identity, so that the generalised eigenproblem ``L phi = lambda M phi`` is the ordinary one
  and the spectral projection onto the constant vector is the vertex centroid.
* cotangent (Pinkall and Polthier 1993, Desbrun et al. 1999; paper ref. [20]):
  ``W(i, j) = 0.5 (cot a_ij + cot b_ij)``, ``a_ij`` and ``b_ij`` the angles opposite the edge in
  its (one or two; any number for a non-manifold edge) faces. ``W(i, j) < 0`` where the
  opposite angles sum to more than pi (obtuse triangles). Its lumped mass is either
  ``"barycentric"`` (a third of the area of each incident face) or ``"voronoi"``: the mixed
  Voronoi area of Meyer et al. 2003 (Voronoi area in non-obtuse faces; half the face area at an
  obtuse corner and a quarter at the two others). Both sum to the total surface area.
* intrinsic (Sharp and Crane 2020, robust-laplacian): the cotangent Laplacian of the intrinsic
  Delaunay triangulation, ``W(i, j) >= 0``, with its lumped vertex areas; the Laplacian of the
  heat kernel signature baseline (:func:`intrinsic_laplacian`).

A face of zero area (collinear corners) has no defined angles: its cotangents are set to 0 (a
warning is logged), so it contributes nothing to ``W``.

Algorithm 2 with these Laplacians (:func:`laplacian_saliency`) forms ``Lhat = |L|`` exactly as
the stochastic construction does (Sec. 3.2, ``Lhat(i, j) = |L(i, j)|``): off the diagonal
``|W(i, j)|``, so a negative cotangent weight becomes positive; on the diagonal
``|D(i, i)| = D(i, i)`` (a cotangent diagonal is a sum over faces of
``0.5 sin(A) / (sin(B) sin(C)) > 0``). A vertex without edges gets ``Lhat(i, i) = 1``, as in
:mod:`stochlap_torch.operators`. ``alpha`` is the library's Eq. 9 and every step is the
library's :func:`~stochlap_torch.diffusion.diffusion_step`; only ``Lhat`` changes.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from .._common.errors import ParameterError
from ..mesh import as_mesh_tensors, face_areas, face_corners, unique_edges
from ..sparse import CSR, symmetric_csr
from .base import MeshOperators
from .heat_operator import intrinsic_delaunay_weights
from .paper import alpha_from_edges

__all__ = [
    "LAPLACIANS",
    "MASS_TYPES",
    "MeshLaplacian",
    "check_laplacian",
    "cotangent_laplacian",
    "face_cotangents",
    "intrinsic_laplacian",
    "laplacian_of_valid_mesh",
    "laplacian_operators",
    "lumped_mass",
    "mesh_laplacian",
    "uniform_laplacian",
]

logger = logging.getLogger(__name__)

#: Names accepted by ``laplacian=`` throughout :mod:`stochlap_torch.baselines`.
LAPLACIANS = ("uniform", "cotangent", "intrinsic")
#: Lumped mass matrices of the cotangent Laplacian.
MASS_TYPES = ("voronoi", "barycentric")


@dataclass(frozen=True)
class MeshLaplacian:
    """``L = D - W`` of a mesh with its lumped (diagonal) mass matrix.

    Attributes:
        kind: one of :data:`LAPLACIANS`.
        edges: ``(E, 2)`` int64 unique undirected edges, ``i < j``, sorted.
        weights: ``(E,)`` float ``W(i, j)`` of each edge (may be negative for the cotangent
            Laplacian, or zero).
        mass: ``(V,)`` float diagonal of the mass matrix ``M`` (ones for the uniform Laplacian,
            zero for a vertex no face references).
    """

    kind: str
    edges: Tensor
    weights: Tensor
    mass: Tensor

    @property
    def num_vertices(self) -> int:
        return int(self.mass.shape[0])

    def degree(self) -> Tensor:
        """``(V,)`` ``D(i, i) = sum_j W(i, j)``."""
        degree = self.weights.new_zeros(self.num_vertices)
        degree.index_add_(0, self.edges[:, 0], self.weights)
        return degree.index_add_(0, self.edges[:, 1], self.weights)

    def stiffness(self) -> CSR:
        """``L = D - W`` as a ``(V, V)`` :class:`~stochlap_torch.sparse.CSR`."""
        return symmetric_csr(self.edges, -self.weights, self.degree())

    def abs_stiffness(self) -> CSR:
        """``Lhat = |L|`` (element-wise); a vertex without edges gets ``Lhat(i, i) = 1``."""
        diagonal = self.degree().abs()
        has_edges = torch.zeros_like(diagonal, dtype=torch.bool)
        has_edges[self.edges.reshape(-1)] = True
        diagonal = torch.where(has_edges, diagonal, torch.ones_like(diagonal))
        return symmetric_csr(self.edges, self.weights.abs(), diagonal)

    def to_dense(self) -> Tensor:
        """``(V, V)`` dense ``L``, for tests and small meshes."""
        return self.stiffness().to_dense()

    def stiffness_scipy(self):
        """``L`` as a float64 ``scipy.sparse.csr_matrix`` (needs scipy)."""
        from scipy import sparse

        matrix = self.stiffness()
        return sparse.csr_matrix(
            (
                matrix.val.detach().cpu().double().numpy(),
                matrix.col.cpu().numpy(),
                matrix.crow.cpu().numpy(),
            ),
            shape=(self.num_vertices, self.num_vertices),
        )

    def mass_scipy(self):
        """``M`` as a float64 diagonal ``scipy.sparse.csr_matrix`` (needs scipy)."""
        from scipy import sparse

        return sparse.diags(self.mass.detach().cpu().double().numpy()).tocsr()


def face_cotangents(vertices: Tensor, faces: Tensor) -> Tensor:
    """Cotangent of the angle at each corner of each face.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int64.

    Returns:
        ``(F, 3)`` float: entry ``(f, c)`` is the cotangent of the angle at corner ``c`` of face
        ``f``, the angle opposite the edge ``(faces[f, c+1], faces[f, c+2])`` (indices mod 3).
        Zero for every corner of a face of zero area (a warning is logged).
    """
    corners = face_corners(vertices, faces)  # (F, 3, 3)
    u = corners.roll(-1, dims=1) - corners
    v = corners.roll(-2, dims=1) - corners
    dot = (u * v).sum(dim=2)
    cross = torch.linalg.cross(u, v, dim=2).norm(dim=2)
    scale = u.norm(dim=2) * v.norm(dim=2)
    degenerate = (cross <= torch.finfo(vertices.dtype).eps * scale).any(dim=1, keepdim=True)
    if bool(degenerate.any()):
        logger.warning(
            "%d faces have zero area; their cotangent weights are set to 0",
            int(degenerate.sum()),
        )
    safe = torch.where(degenerate, torch.ones_like(cross), cross)
    return torch.where(degenerate, torch.zeros_like(dot), dot / safe)


def lumped_mass(vertices, faces, kind: str = "voronoi") -> Tensor:
    """Diagonal of a lumped mass matrix: the area attributed to each vertex.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` integer.
        kind: ``"voronoi"`` (mixed Voronoi areas, Meyer et al. 2003) or ``"barycentric"``
            (a third of each incident face).

    Returns:
        ``(V,)`` float in the dtype of ``vertices``; sums to the total face area; zero for a
        vertex no face references.
    """
    if kind not in MASS_TYPES:
        raise ParameterError(f"mass must be one of {MASS_TYPES}, got {kind!r}")
    vertices, faces = as_mesh_tensors(vertices, faces)
    return _lumped_mass(vertices, faces, kind)


def _lumped_mass(vertices: Tensor, faces: Tensor, kind: str) -> Tensor:
    """:func:`lumped_mass` of checked tensors."""
    areas = face_areas(vertices, faces)
    if kind == "barycentric":
        shares = (areas / 3.0).unsqueeze(1).expand(-1, 3)
    else:
        shares = _mixed_voronoi_shares(vertices, faces, areas)
    mass = vertices.new_zeros(vertices.shape[0])
    return mass.index_add_(0, faces.reshape(-1), shares.reshape(-1))


def _mixed_voronoi_shares(vertices: Tensor, faces: Tensor, areas: Tensor) -> Tensor:
    """``(F, 3)`` mixed Voronoi area of each corner (Meyer et al. 2003, Fig. 4)."""
    cot = face_cotangents(vertices, faces)
    corners = face_corners(vertices, faces)
    # Squared length of the edge opposite each corner: corner c faces (c+1, c+2).
    opposite_sq = (corners.roll(-1, dims=1) - corners.roll(-2, dims=1)).square().sum(dim=2)
    # Voronoi area of corner c: (|c c+1|^2 cot(c+2) + |c c+2|^2 cot(c+1)) / 8, where
    # |c c+1| is the edge opposite corner c+2 and |c c+2| the one opposite corner c+1.
    voronoi = (
        opposite_sq.roll(-2, dims=1) * cot.roll(-2, dims=1)
        + opposite_sq.roll(-1, dims=1) * cot.roll(-1, dims=1)
    ) / 8.0
    obtuse_corner = cot < 0
    obtuse_face = obtuse_corner.any(dim=1, keepdim=True)
    area = areas.unsqueeze(1)
    fallback = torch.where(obtuse_corner, area / 2.0, area / 4.0)
    return torch.where(obtuse_face, fallback, voronoi)


def check_laplacian(kind: str) -> None:
    """Raise ``ValueError`` unless ``kind`` is one of :data:`LAPLACIANS`."""
    if kind not in LAPLACIANS:
        raise ParameterError(f"laplacian must be one of {LAPLACIANS}, got {kind!r}")


def uniform_laplacian(vertices, faces) -> MeshLaplacian:
    """The uniform (graph) Laplacian: ``W(i, j) = 1`` on edges, identity mass.

    Args:
        vertices: ``(V, 3)`` float (only ``V`` and the dtype are used).
        faces: ``(F, 3)`` integer.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    return _uniform_laplacian(vertices, faces)


def _uniform_laplacian(vertices: Tensor, faces: Tensor) -> MeshLaplacian:
    """:func:`uniform_laplacian` of checked tensors."""
    edges = unique_edges(faces, vertices.shape[0])
    weights = vertices.new_ones(edges.shape[0])
    return MeshLaplacian("uniform", edges, weights, vertices.new_ones(vertices.shape[0]))


def cotangent_laplacian(vertices, faces, mass: str = "voronoi") -> MeshLaplacian:
    """The cotangent Laplacian ``W(i, j) = 0.5 (cot a_ij + cot b_ij)`` with a lumped mass.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` integer.
        mass: ``"voronoi"`` or ``"barycentric"``, see :func:`lumped_mass`.

    Returns:
        A :class:`MeshLaplacian` in the dtype of ``vertices``. A boundary edge gets half the
        cotangent of its single opposite angle; a non-manifold edge the sum over its faces.
    """
    if mass not in MASS_TYPES:
        raise ParameterError(f"mass must be one of {MASS_TYPES}, got {mass!r}")
    vertices, faces = as_mesh_tensors(vertices, faces)
    return _cotangent_laplacian(vertices, faces, mass)


def _cotangent_laplacian(vertices: Tensor, faces: Tensor, mass: str) -> MeshLaplacian:
    """:func:`cotangent_laplacian` of checked tensors."""
    num_vertices = vertices.shape[0]
    edges = unique_edges(faces, num_vertices)
    cot = face_cotangents(vertices, faces)
    # Corner c is opposite the edge (c+1, c+2).
    first, second = faces.roll(-1, dims=1).reshape(-1), faces.roll(-2, dims=1).reshape(-1)
    keys = torch.minimum(first, second) * num_vertices + torch.maximum(first, second)
    edge_keys = edges[:, 0] * num_vertices + edges[:, 1]
    slot = torch.searchsorted(edge_keys, keys)
    weights = vertices.new_zeros(edges.shape[0]).index_add_(0, slot, 0.5 * cot.reshape(-1))
    return MeshLaplacian("cotangent", edges, weights, _lumped_mass(vertices, faces, mass))


def mesh_laplacian(vertices, faces, laplacian: str = "cotangent", mass: str = "voronoi"):
    """:func:`uniform_laplacian`, :func:`cotangent_laplacian` or :func:`intrinsic_laplacian`
    by name.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` integer.
        laplacian: one of :data:`LAPLACIANS`.
        mass: the cotangent Laplacian's lumped mass (ignored for ``"uniform"`` and
            ``"intrinsic"``, whose masses are the identity and the intrinsic vertex areas).

    Returns:
        A :class:`MeshLaplacian`.
    """
    check_laplacian(laplacian)
    if mass not in MASS_TYPES:
        raise ParameterError(f"mass must be one of {MASS_TYPES}, got {mass!r}")
    vertices, faces = as_mesh_tensors(vertices, faces)
    return laplacian_of_valid_mesh(vertices, faces, laplacian, mass)


def intrinsic_laplacian(vertices, faces) -> MeshLaplacian:
    """The cotangent Laplacian of the intrinsic Delaunay triangulation (robust-laplacian).

    Its weights are never negative and its eigenpairs barely change under remeshing, which
    makes it the Laplacian of the heat kernel signature baseline the robust variant is
    compared with. Computed in float64 by robust-laplacian (no gradient flows through it) and
    returned in the dtype and on the device of ``vertices``; ``edges`` are the intrinsic
    triangulation's, which may join vertices that no face joins; ``mass`` holds its lumped
    vertex areas.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` integer.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    return _intrinsic_laplacian(vertices, faces)


def _intrinsic_laplacian(vertices: Tensor, faces: Tensor) -> MeshLaplacian:
    """:func:`intrinsic_laplacian` of checked tensors."""
    edges, weights, mass = intrinsic_delaunay_weights(
        vertices.detach().cpu().double().numpy(), faces.cpu().numpy()
    )
    to = {"dtype": vertices.dtype, "device": vertices.device}
    return MeshLaplacian(
        "intrinsic",
        torch.from_numpy(edges).to(vertices.device),
        torch.from_numpy(weights).to(**to),
        torch.from_numpy(mass).to(**to),
    )


def laplacian_of_valid_mesh(vertices: Tensor, faces: Tensor, laplacian: str, mass: str):
    """:func:`mesh_laplacian` of validated tensors and checked names."""
    if laplacian == "uniform":
        return _uniform_laplacian(vertices, faces)
    if laplacian == "intrinsic":
        return _intrinsic_laplacian(vertices, faces)
    return _cotangent_laplacian(vertices, faces, mass)


def laplacian_operators(vertices, faces, laplacian: str = "uniform") -> MeshOperators:
    """The library's :class:`~stochlap_torch.operators.MeshOperators` with ``Lhat = |L|`` of
    the uniform or cotangent Laplacian in place of ``|D - W|``, ``W = 1 / |Pi - Pj|^2``.

    ``alpha`` is the library's Eq. 9, unchanged (see the module docstring for ``|L|``).

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` integer.
        laplacian: one of :data:`LAPLACIANS`.
    """
    check_laplacian(laplacian)
    vertices, faces = as_mesh_tensors(vertices, faces)
    lap = laplacian_of_valid_mesh(vertices, faces, laplacian, "voronoi")
    return MeshOperators(lap.abs_stiffness(), alpha_from_edges(vertices, lap.edges))

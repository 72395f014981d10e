"""The uniform, cotangent and intrinsic Delaunay mesh Laplacians with lumped masses (paper
Fig. 11).

Each is ``L = D - W`` on undirected edges, ``D(i, i) = sum_j W(i, j)``, symmetric, ``L 1 = 0``:

* uniform (Taubin 1995): ``W(i, j) = 1`` on every edge, identity mass (the generalised
  eigenproblem is the ordinary one);
* cotangent (Pinkall and Polthier 1993): ``W(i, j) = 0.5 (cot a_ij + cot b_ij)`` over the
  edge's faces, negative where the opposite angles sum to more than pi; lumped mass
  ``"barycentric"`` (a third of each incident face) or ``"voronoi"`` (the mixed Voronoi area of
  Meyer et al. 2003); a face of zero area gets cotangents 0 (with a warning);
* intrinsic (Sharp and Crane 2020): the cotangent Laplacian of the intrinsic Delaunay
  triangulation, ``W(i, j) >= 0``, with its vertex areas (the heat kernel signature's).

Algorithm 2 runs on them with ``Lhat = |L|`` (:func:`laplacian_operators`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import torch
from torch import Tensor

from .._common.errors import ParameterError
from .._kernels import intrinsic_delaunay_weights
from ..mesh import as_mesh_tensors, face_areas, face_corners, unique_edges
from ..sparse import CSR, symmetric_csr
from .paper import MeshOperators, alpha_from_edges

__all__ = [
    "LAPLACIANS",
    "MASS_TYPES",
    "MeshLaplacian",
    "cotangent_laplacian",
    "face_cotangents",
    "intrinsic_laplacian",
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
        """``Lhat = |L|`` as the paper takes it (Sec. 3.2), element-wise; a vertex without
        edges gets ``Lhat(i, i) = 1``."""
        diagonal = self.degree().abs()
        has_edges = torch.zeros_like(diagonal, dtype=torch.bool)
        has_edges[self.edges.reshape(-1)] = True
        diagonal = torch.where(has_edges, diagonal, torch.ones_like(diagonal))
        return symmetric_csr(self.edges, self.weights.abs(), diagonal)

    def to_dense(self) -> Tensor:
        """``(V, V)`` dense ``L``."""
        return self.stiffness().to_dense()

    def stiffness_scipy(self):
        """``L`` as a float64 ``scipy.sparse.csr_matrix`` (needs scipy)."""
        from scipy import sparse

        matrix, size = self.stiffness(), self.num_vertices
        arrays = (matrix.val.detach().cpu().double(), matrix.col.cpu(), matrix.crow.cpu())
        return sparse.csr_matrix(tuple(a.numpy() for a in arrays), shape=(size, size))


def face_cotangents(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3)`` float cotangent of the angle at corner ``c`` of face ``f``, opposite the edge
    ``(faces[f, c+1], faces[f, c+2])`` (indices mod 3); zero on a face of zero area (with a
    warning)."""
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


def _check_name(option: str, value: str, names: tuple[str, ...]) -> None:
    if value not in names:
        raise ParameterError(f"{option} must be one of {names}, got {value!r}")


def check_laplacian(kind: str) -> None:
    """Raise :class:`ParameterError` unless ``kind`` is one of :data:`LAPLACIANS`."""
    _check_name("laplacian", kind, LAPLACIANS)


def lumped_mass(vertices, faces, kind: str = "voronoi") -> Tensor:
    """``(V,)`` diagonal of a lumped mass matrix, the area of each vertex, in the dtype of
    ``vertices`` ``(V, 3)``: ``kind`` ``"voronoi"`` or ``"barycentric"``; sums to the surface
    area, zero for a vertex no face of ``faces`` ``(F, 3)`` references."""
    _check_name("mass", kind, MASS_TYPES)
    return _lumped_mass(*as_mesh_tensors(vertices, faces), kind)


def _lumped_mass(vertices: Tensor, faces: Tensor, kind: str) -> Tensor:
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


def uniform_laplacian(vertices, faces) -> MeshLaplacian:
    """The uniform (graph) Laplacian of ``(V, 3)`` float ``vertices`` (only ``V`` and the
    dtype are used) and ``(F, 3)`` integer ``faces``."""
    return laplacian_of_valid_mesh(*as_mesh_tensors(vertices, faces), "uniform", "voronoi")


def cotangent_laplacian(vertices, faces, mass: str = "voronoi") -> MeshLaplacian:
    """The cotangent Laplacian of ``(V, 3)`` float ``vertices`` and ``(F, 3)`` integer
    ``faces`` with the lumped ``mass`` (:func:`lumped_mass`). A boundary edge gets half the
    cotangent of its one opposite angle, a non-manifold edge the sum over its faces."""
    _check_name("mass", mass, MASS_TYPES)
    return laplacian_of_valid_mesh(*as_mesh_tensors(vertices, faces), "cotangent", mass)


def intrinsic_laplacian(vertices, faces) -> MeshLaplacian:
    """The intrinsic Laplacian of ``(V, 3)`` float ``vertices`` and ``(F, 3)`` integer
    ``faces``, computed in float64 (no gradient flows through it) and returned in the dtype
    and on the device of ``vertices``; its ``edges`` are the intrinsic triangulation's (they
    may join vertices no face joins)."""
    return laplacian_of_valid_mesh(*as_mesh_tensors(vertices, faces), "intrinsic", "voronoi")


def mesh_laplacian(vertices, faces, laplacian: str = "cotangent", mass: str = "voronoi"):
    """The :class:`MeshLaplacian` named ``laplacian`` (one of :data:`LAPLACIANS`) of
    ``(V, 3)`` float ``vertices`` and ``(F, 3)`` integer ``faces``; ``mass`` is the cotangent
    Laplacian's lumped mass (the others have the identity and the intrinsic vertex areas)."""
    check_laplacian(laplacian)
    _check_name("mass", mass, MASS_TYPES)
    return laplacian_of_valid_mesh(*as_mesh_tensors(vertices, faces), laplacian, mass)


def laplacian_of_valid_mesh(vertices: Tensor, faces: Tensor, laplacian: str, mass: str):
    """:func:`mesh_laplacian` of validated tensors and checked names."""
    if laplacian == "intrinsic":
        edges, weights, areas = intrinsic_delaunay_weights(
            vertices.detach().cpu().double().numpy(), faces.cpu().numpy()
        )
        to = {"dtype": vertices.dtype, "device": vertices.device}
        edges = torch.from_numpy(edges).to(vertices.device)
        return MeshLaplacian(
            "intrinsic", edges, torch.from_numpy(weights).to(**to), torch.from_numpy(areas).to(**to)
        )
    num_vertices = vertices.shape[0]
    edges = unique_edges(faces, num_vertices)
    if laplacian == "uniform":
        ones = vertices.new_ones(num_vertices)
        return MeshLaplacian("uniform", edges, vertices.new_ones(edges.shape[0]), ones)
    cot = face_cotangents(vertices, faces)
    # Corner c is opposite the edge (c+1, c+2).
    first, second = faces.roll(-1, dims=1).reshape(-1), faces.roll(-2, dims=1).reshape(-1)
    keys = torch.minimum(first, second) * num_vertices + torch.maximum(first, second)
    edge_keys = edges[:, 0] * num_vertices + edges[:, 1]
    slot = torch.searchsorted(edge_keys, keys)
    weights = vertices.new_zeros(edges.shape[0]).index_add_(0, slot, 0.5 * cot.reshape(-1))
    return MeshLaplacian("cotangent", edges, weights, _lumped_mass(vertices, faces, mass))


def laplacian_operators(vertices, faces, laplacian: str = "uniform") -> MeshOperators:
    """:class:`~stochlap_torch.operators.MeshOperators` of ``(V, 3)`` float ``vertices`` and
    ``(F, 3)`` integer ``faces`` with ``Lhat = |L|`` of the Laplacian named ``laplacian`` (one
    of :data:`LAPLACIANS`) in place of ``|D - W|``; ``alpha`` is Eq. 9, unchanged."""
    check_laplacian(laplacian)
    vertices, faces = as_mesh_tensors(vertices, faces)
    lap = laplacian_of_valid_mesh(vertices, faces, laplacian, "voronoi")
    return MeshOperators(lap.abs_stiffness(), alpha_from_edges(vertices, lap.edges))

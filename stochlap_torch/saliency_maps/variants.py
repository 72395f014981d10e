"""Saliency variants built on the same multiscale representation (Algorithm 1).

Algorithm 2's difference maps ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)`` depend on the
triangulation: the operator sees edge lengths only, so the number of neighbours of a vertex
(its valence) sets how many terms its rows hold and how its probability mass spreads. On an
irregular mesh the paper's saliency therefore partly maps the valence (see
``docs/RESULTS_EVALUATION.md``). The variants here keep Algorithm 1 as it is (one call to
:func:`~stochlap_torch.diffusion.multiscale_representation`, so the same cost) and change only
how the per-scale outputs become a saliency:

* ``"paper"``: Algorithm 2, ``log(sum_{k>=2} D^(k))``.
* ``"normal_coefficients"``: the coefficients ``C^(k) = P^(k-1) - P^(k)`` projected on the
  vertex normal ``n_i`` and divided by the mean length ``l_i`` of the edges at vertex ``i``,
  ``log(sum_{k>=2} |C^(k)(i) . n_i| / l_i)``: how far the surface moves *out of its tangent
  plane* between scales, in units of the local sampling (scale and rotation invariant; the
  triangulation's tangential drift does not count).
* ``"normal_displacement"``: the signed total displacement along the outward normal,
  ``(P - P^(K))(i) . n_i / l_i = sum_{k>=2} C^(k)(i) . n_i / l_i`` (no logarithm: it is signed).
  Tips and ridges score high, concave creases low; summing before taking a magnitude cancels
  the triangulation's scale-to-scale jitter. "Outward" is fixed per mesh by the sign of the
  volume enclosed (open meshes: against the centroid).
* ``"valence_normalised"``: each difference map divided by its typical value for the vertex's
  valence, estimated on the mesh itself: ``log(sum_{k>=2} D^(k)(i) / m_k(v_i))`` with
  ``m_k(v)`` the (lower) median of ``D^(k)`` over the vertices of valence ``v`` (valences held
  by fewer than ``min_count`` vertices borrow the median of the nearest valence that has
  enough).

Every variant returns a finite ``(V,)`` saliency; vertices with no edges get the smallest
saliency of the other vertices of their mesh, as in
:func:`~stochlap_torch.diffusion.saliency_from_differences`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._common.checks import check_choice
from .._common.errors import ParameterError
from .._common.variants import VARIANTS
from ..diffusion import MultiscaleRepresentation, saliency_from_differences
from ..mesh import outward_sign, vertex_mean_edge_length, vertex_normals, vertex_valence

#: Valences held by fewer vertices than this borrow the median of the nearest populated one.
DEFAULT_MIN_COUNT = 30
#: The variants that read ``P^(k)``; the others need the difference maps alone.
POSITION_VARIANTS = ("normal_coefficients", "normal_displacement")


def _nearest_populated(counts: Tensor, min_count: int) -> Tensor:
    """For every valence ``0..len(counts)-1`` of one mesh, the nearest valence held by at least
    ``min_count`` vertices (the most frequent valence if none is); ``(N,)`` int64."""
    valences = torch.arange(counts.numel(), device=counts.device)
    populated = (counts >= min_count) & (valences > 0)
    if not bool(populated.any()):
        held = torch.where(valences > 0, counts, torch.zeros_like(counts))
        if int(held.max()) == 0:  # no vertex has an edge
            return valences
        populated = valences == int(held.argmax())
    candidates = valences[populated]
    gap = (valences.unsqueeze(1) - candidates.unsqueeze(0)).abs()
    return candidates[gap.argmin(dim=1)]


def valence_normalised_differences(
    differences: Tensor,
    valence: Tensor,
    batch: Tensor | None = None,
    min_count: int = DEFAULT_MIN_COUNT,
) -> Tensor:
    """Difference maps divided by their median over the vertices of the same valence.

    Args:
        differences: ``(K, V)`` ``D^(k)``, ``differences[0] = 0``.
        valence: ``(V,)`` int64 valence of every vertex (:func:`vertex_valence`).
        batch: optional ``(V,)`` int64 mesh index: medians are taken per mesh (``None``: one).
        min_count: a valence held by fewer vertices (of its mesh) borrows the median of the
            nearest valence held by at least this many.

    Returns:
        ``(K, V)`` non-negative maps; rows of vertices without edges stay 0.
    """
    if min_count < 1:
        raise ParameterError(f"min_count must be >= 1, got {min_count}")
    num_vertices = differences.shape[1]
    if batch is None:
        batch = torch.zeros(num_vertices, dtype=torch.int64, device=differences.device)
    width = int(valence.max()) + 1 if num_vertices else 1
    out = torch.zeros_like(differences)
    for mesh in range(int(batch.max()) + 1 if num_vertices else 0):
        members = (batch == mesh).nonzero().flatten()
        mesh_valence = valence[members]
        counts = torch.bincount(mesh_valence, minlength=width)
        group = _nearest_populated(counts, min_count)[mesh_valence]  # (n,)
        for value in torch.unique(group).tolist():
            inside = members[group == value]
            source = members[(mesh_valence == value) & (mesh_valence > 0)]
            if source.numel() == 0:
                continue
            median = differences[:, source].median(dim=1).values  # (K,)
            usable = median > 0
            safe = torch.where(usable, median, torch.ones_like(median))
            scaled = differences[:, inside] / safe.unsqueeze(1)
            out[:, inside] = torch.where(usable.unsqueeze(1), scaled, torch.zeros_like(scaled))
    out[:, valence == 0] = 0.0
    return out


def saliency_from_representation(
    rep: MultiscaleRepresentation,
    vertices: Tensor,
    faces: Tensor,
    variant: str = "paper",
    min_count: int = DEFAULT_MIN_COUNT,
) -> Tensor:
    """A variant's saliency from an already computed multiscale representation.

    Args:
        rep: output of :func:`~stochlap_torch.diffusion.multiscale_representation` on
            ``vertices`` and ``faces`` (with its ``batch`` if it was a packed batch).
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` int64 tensor.
        variant: one of :data:`VARIANTS`.
        min_count: see :func:`valence_normalised_differences`.

    Returns:
        ``(V,)`` finite saliency in the dtype of ``vertices``.
    """
    check_choice("variant", variant, VARIANTS)
    if variant == "robust":
        raise ParameterError(
            "the robust saliency comes from its own representation: "
            "robust_saliency(robust_representation(vertices, faces)), or saliency(...)"
        )
    if rep.differences.shape[1] != vertices.shape[0]:
        raise ParameterError(
            f"the representation has {rep.differences.shape[1]} vertices, the mesh "
            f"{vertices.shape[0]}"
        )
    if variant == "paper":
        return rep.saliency()
    vertices = vertices.detach()
    if variant == "valence_normalised":
        valence = vertex_valence(faces, vertices.shape[0])
        maps = valence_normalised_differences(rep.differences, valence, rep.batch, min_count)
    else:
        # Per mean incident edge length l_i; 0 at a vertex without edges.
        normals = vertex_normals(vertices, faces)
        edge_length = vertex_mean_edge_length(vertices, faces)
        safe = torch.where(edge_length > 0, edge_length, torch.ones_like(edge_length))
        if variant == "normal_displacement":
            normals = normals * outward_sign(vertices, faces, rep.batch)[:, None]
            along = ((rep.positions[0] - rep.positions[-1]).detach() * normals).sum(dim=1)
            return torch.where(edge_length > 0, along / safe, torch.zeros_like(along))
        normal = (rep.coefficients.detach() * normals.unsqueeze(0)).sum(dim=2).abs()  # (K, V)
        maps = torch.where(edge_length > 0, normal / safe, torch.zeros_like(normal))
    maps = maps.clone()
    maps[0] = 0.0  # scale 1 is excluded, as in Algorithm 2
    return saliency_from_differences(maps, rep.batch)

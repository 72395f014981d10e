"""Per-vertex features of the paper's multiscale representation (``variant="paper"``).

:func:`paper_features` turns the representation of a mesh (or of a packed batch) into a
``(V, C)`` feature matrix. The channels come in groups, always in this order (scales
``k = 2..K``; scale 1 is the input, whose coefficient is zero and is left out):

=================  ======================  ===============================================
group              channels                names
=================  ======================  ===============================================
``coefficients``   ``3 (K-1)``             ``coef{k}_x``, ``coef{k}_y``, ``coef{k}_z``
  (rotation inv.)  ``2 (K-1)``             ``coef{k}_normal``, ``coef{k}_tangent``
``norms``          ``K-1``                 ``coef{k}_norm``
``differences``    ``K-1``                 ``diff{k}``
``saliency``       ``1``                   ``saliency``
=================  ======================  ===============================================

Within the coefficient group the channels are ordered scale-major (all channels of scale 2,
then scale 3, ...). :func:`paper_channel_names` lists them.

Invariances: the coefficients ``C^(k) = P^(k-1) - P^(k)`` are translation invariant and scale
with the mesh; divided per mesh by a length (the mean edge length by default), every channel is
scale invariant. With ``rotation_invariant=True`` a coefficient is its component along the
vertex normal (area-weighted, following the face orientation) and its tangential norm.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._common.checks import check_choice
from ..diffusion import differentiable_multiscale, multiscale_representation
from ..mesh import as_mesh_tensors, check_batch, extent_scale, mean_edge_length, mesh_extent
from ..mesh.geometry import safe_norm, unique_edges, vertex_normals
from ..params import NORMALISATIONS, PaperFeatureParams


def mesh_lengths(
    vertices: Tensor, faces: Tensor, batch: Tensor | None = None, kind: str = "mean_edge"
) -> Tensor:
    """``(B,)`` one length per mesh of a packed batch (``B = 1`` without ``batch``).

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int64.
        batch: optional ``(V,)`` int64 mesh index of every vertex (``None``: one mesh).
        kind: ``"mean_edge"`` (mean length of the unique edges), ``"bbox_diagonal"`` (diagonal
            of the axis-aligned bounding box of the vertices) or ``"none"`` (ones).
    """
    check_choice("normalisation", kind, NORMALISATIONS)
    if kind == "none":
        num_meshes = int(batch.max()) + 1 if batch is not None and batch.numel() else 1
        return vertices.new_ones(num_meshes)
    if kind == "bbox_diagonal":
        lengths = mesh_extent(vertices, batch)
    else:
        lengths = mean_edge_length(vertices, unique_edges(faces, vertices.shape[0]), batch)
    # A mesh without edges or extent (a single point) keeps its units.
    return torch.where(torch.isfinite(lengths) & (lengths > 0), lengths, torch.ones_like(lengths))


def _group_channel_names(group: str, params: PaperFeatureParams) -> list[str]:
    scales = range(2, params.num_scales + 1)
    if group == "coefficients":
        parts = ("normal", "tangent") if params.rotation_invariant else ("x", "y", "z")
        return [f"coef{k}_{part}" for k in scales for part in parts]
    if group == "norms":
        return [f"coef{k}_norm" for k in scales]
    if group == "differences":
        return [f"diff{k}" for k in scales]
    return ["saliency"]


def paper_channel_names(params: PaperFeatureParams) -> list[str]:
    """Names of the channels :func:`paper_features` returns with ``params``, in order."""
    return [name for group in params.include for name in _group_channel_names(group, params)]


def paper_features(
    vertices,
    faces,
    params: PaperFeatureParams | None = None,
    batch: Tensor | None = None,
    max_memory: int | None = None,
) -> Tensor:
    """``(V, C)`` per-vertex features of the paper's representation of a mesh or packed batch.

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        params: the options (default :class:`~stochlap_torch.params.PaperFeatureParams`).
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch.
        max_memory: byte budget for the operators.

    Returns:
        ``(V, C)`` float in the dtype of ``vertices``, in the channel order of
        :func:`paper_channel_names`.
    """
    params = PaperFeatureParams() if params is None else params
    points, faces = as_mesh_tensors(vertices, faces)
    if batch is not None:
        batch = check_batch(batch, points.shape[0], faces)
    # Every channel is scale invariant: compute at a safe size (an exact power-of-two scale).
    scale = extent_scale(points)
    points = points if scale == 1.0 else points * scale
    run = differentiable_multiscale if params.differentiable_operator else multiscale_representation
    rep = run(
        points, faces, params.num_scales, params.threshold, batch=batch, max_memory=max_memory
    )
    # Normals and lengths of the representation's own P (what the gradient path sees).
    points, num_vertices = rep.positions[0], points.shape[0]
    lengths = mesh_lengths(points, faces, batch, params.normalisation)
    per_vertex = lengths[batch] if batch is not None else lengths.expand(num_vertices)
    coefficients = rep.coefficients[1:] / per_vertex.reshape(1, -1, 1)  # (K-1, V, 3)
    channels = []
    if "coefficients" in params.include:
        local = coefficients
        if params.rotation_invariant:
            normals = vertex_normals(points, faces)
            normal = (coefficients * normals).sum(dim=2)
            tangent = safe_norm(coefficients - normal.unsqueeze(2) * normals, dim=2)
            local = torch.stack([normal, tangent], dim=2)  # (K-1, V, 2)
        channels.append(local.permute(1, 0, 2).reshape(num_vertices, -1))
    if "norms" in params.include:
        channels.append(safe_norm(coefficients, dim=2).T)
    if "differences" in params.include:
        channels.append(rep.differences[1:].T)
    if "saliency" in params.include:
        channels.append(rep.saliency().unsqueeze(1))
    return torch.cat(channels, dim=1)

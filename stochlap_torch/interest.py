"""Interest points from a saliency field (paper Sec. 4.5).

* ``"paper"``: every vertex whose saliency is ``>=`` that of each 1-ring neighbour and at
  least ``t_global`` of the way from the minimum to the maximum. (The paper's global test,
  ``I >= T_global I_max / I_std``, means nothing for a saliency that is a logarithm and can
  be negative.) Hundreds of points on a 10k-vertex mesh.
* ``"nms"`` (default): the same candidates from the most salient down, each kept unless a
  kept point lies within ``radius`` (a fraction of the bounding-box diagonal) along the edges
  of the mesh: a few tens of well separated points, closer to what people mark by hand.

A saliency equal on every vertex (the robust saliency of an exactly flat plate) gives no
point. The robust saliency is standardised per mesh, so on a featureless surface noise is
amplified: a plate with ``1e-12`` of noise gets points.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ._common.checks import check_choice, check_number, check_optional_int, refuse_unused
from ._common.errors import ParameterError
from ._common.variants import DEFAULT_RADIUS, DEFAULT_T_GLOBAL
from .mesh import as_mesh_tensors, check_batch, unique_edges
from .mesh.geometry import edge_graph

__all__ = [
    "DEFAULT_RADIUS",
    "DEFAULT_T_GLOBAL",
    "INTEREST_MODES",
    "check_interest_parameters",
    "interest_points",
]

INTEREST_MODES = ("nms", "paper")


def _candidates(saliency: Tensor, edges: Tensor, t_global: float) -> Tensor:
    """Paper-mode points, most salient first (ties broken by vertex index); none where the
    saliency is the same on every vertex of the surface (nothing stands out)."""
    on_surface = torch.zeros_like(saliency, dtype=torch.bool)
    on_surface[edges.reshape(-1)] = True
    low, high = saliency[on_surface].min(), saliency[on_surface].max()
    if not bool(high > low):
        return edges.new_zeros(0)
    neighbour_max = saliency.new_full(saliency.shape, -torch.inf)  # over the 1-ring
    neighbour_max.scatter_reduce_(0, edges[:, 0], saliency[edges[:, 1]], reduce="amax")
    neighbour_max.scatter_reduce_(0, edges[:, 1], saliency[edges[:, 0]], reduce="amax")
    maxima = (saliency >= neighbour_max) & torch.isfinite(neighbour_max)
    strong = saliency >= low + t_global * (high - low)
    chosen = (maxima & strong).nonzero().flatten()
    order = torch.argsort(saliency[chosen], descending=True, stable=True)
    return chosen[order]


def check_interest_parameters(
    mode: str, radius: float | None, top_k: int | None, t_global: float
) -> tuple[str, float | None, int | None, float]:
    """``(mode, radius, top_k, t_global)`` checked (:class:`ParameterError` naming the bad
    one): a mode of :data:`INTEREST_MODES`, ``top_k`` a positive integer or ``None``,
    ``0 <= t_global <= 1``; for ``"nms"`` a finite ``radius > 0`` (default
    :data:`DEFAULT_RADIUS`), for ``"paper"``, which suppresses nothing, no ``radius``
    (``None`` returned)."""
    check_choice("mode", mode, INTEREST_MODES)
    if mode == "paper":
        refuse_unused(mode, {"radius": radius}, name="mode")
    else:
        radius = DEFAULT_RADIUS if radius is None else radius
        radius = check_number("radius", radius, 0.0, None, open_low=True)
    top_k = check_optional_int("top_k", top_k, minimum=1)
    t_global = check_number("t_global", t_global, 0.0, 1.0)
    return mode, radius, top_k, t_global


def interest_points(
    saliency: Tensor,
    vertices,
    faces,
    mode: str = "nms",
    radius: float | None = None,
    top_k: int | None = None,
    t_global: float = DEFAULT_T_GLOBAL,
    batch: Tensor | None = None,
) -> Tensor:
    """Interest points of a saliency field, most salient first.

    Args:
        saliency: ``(V,)`` float saliency, e.g. from
            :func:`~stochlap_torch.saliency_maps.mesh_saliency`.
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        mode: ``"nms"`` (default) or ``"paper"``, see the module docstring.
        radius: suppression radius for ``"nms"``, as a fraction of the bounding-box diagonal
            of the referenced vertices (default :data:`DEFAULT_RADIUS`; ``"paper"`` refuses
            it).
        top_k: keep at most this many points (``None``: no cap).
        t_global: fraction of the saliency range a point must reach (0.4 in the paper).
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch: points are
            found in each mesh on its own (``top_k`` per mesh) and listed mesh by mesh.

    Returns:
        ``(N,)`` int64 vertex indices on the device of ``saliency``; empty for a mesh whose
        saliency is the same on every vertex (see the module docstring).
    """
    mode, radius, top_k, t_global = check_interest_parameters(mode, radius, top_k, t_global)
    vertices, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=False)
    if not isinstance(saliency, Tensor):
        try:
            saliency = torch.as_tensor(saliency, device=vertices.device)
        except (TypeError, ValueError, RuntimeError) as exc:
            raise ParameterError(f"saliency could not be read as a (V,) array: {exc}") from exc
    if not saliency.is_floating_point():
        raise ParameterError(f"saliency must hold real numbers, got {saliency.dtype}")
    if saliency.shape != (vertices.shape[0],):
        raise ParameterError(
            f"saliency must have shape ({vertices.shape[0]},), got {tuple(saliency.shape)}"
        )
    if not bool(torch.isfinite(saliency).all()):
        raise ParameterError("saliency holds NaN or Inf values")
    saliency, faces = saliency.detach(), faces.to(saliency.device)
    options = (mode, radius, top_k, t_global)
    if batch is None:
        return _mesh_points(saliency, vertices, faces, *options)
    batch = check_batch(batch, vertices.shape[0], faces)
    face_mesh = batch[faces[:, 0]]
    found = []
    for mesh in torch.unique(batch).tolist():  # the labels in use, however large
        members = (batch == mesh).nonzero().flatten()
        local = torch.full_like(batch, -1)
        local[members] = torch.arange(members.numel(), device=members.device)
        mesh_faces = local[faces[face_mesh == mesh]]
        if mesh_faces.numel():
            chosen = _mesh_points(saliency[members], vertices[members], mesh_faces, *options)
            found.append(members[chosen])
    return torch.cat(found) if found else faces.new_zeros(0)


def _mesh_points(saliency, vertices, faces, mode, radius, top_k, t_global) -> Tensor:
    """Interest points of one mesh (:func:`interest_points`, of validated tensors)."""
    edges = unique_edges(faces, vertices.shape[0])
    candidates = _candidates(saliency, edges, t_global)
    if mode == "paper":
        return candidates if top_k is None else candidates[:top_k]
    # Greedy non-maximum suppression within ``radius`` of the bounding-box diagonal.
    from scipy.sparse.csgraph import dijkstra

    points = vertices.detach().cpu().double().numpy()
    edge_array = edges.cpu().numpy()
    on_surface = np.unique(edge_array)
    extent = points[on_surface].max(axis=0) - points[on_surface].min(axis=0)
    reach = radius * float(np.linalg.norm(extent))
    graph = edge_graph(points, edge_array)
    suppressed = np.zeros(points.shape[0], dtype=bool)
    kept: list[int] = []
    for vertex in candidates.tolist():
        if top_k is not None and len(kept) >= top_k:
            break
        if suppressed[vertex]:
            continue
        kept.append(vertex)
        # The ball of graph-geodesic radius ``reach``: Dijkstra stopped at that distance.
        suppressed[np.isfinite(dijkstra(graph, indices=vertex, limit=reach))] = True
    return torch.tensor(kept, dtype=torch.int64, device=saliency.device)

"""Interest points from a saliency field (paper Sec. 4.5).

* ``"paper"``: every vertex whose saliency is ``>=`` that of each 1-ring neighbour and at
  least ``t_global`` of the way from the minimum to the maximum. (The paper's global test,
  ``I >= T_global I_max / I_std``, means nothing for a saliency that is a logarithm and can
  be negative.) Hundreds of points on a 10k-vertex mesh.
* ``"nms"`` (default): the same candidates from the most salient down, each kept unless a
  kept point lies within ``radius`` (a fraction of the bounding-box diagonal) along the edges
  of the mesh: a few tens of well separated points, closer to what people mark by hand.

Vertices on the rim of a hole (an edge that one face alone uses) are not interest points
unless ``include_boundary=True``: a scan's open bottom or a cut makes the saliency jump along
the rim, which says nothing about the shape. The rim still counts as the neighbour of the
ring inside it, so that ring gets no point from the jump either.

When ``top_k`` asks for more points than the detector finds, an
:class:`InterestPointWarning` says how many it found and why: too few local maxima reach
``t_global``, or the suppression radius leaves no room, with the radius that would give
``top_k``.

A saliency equal on every vertex (the robust saliency of an exactly flat plate) gives no
point. The robust saliency is standardised per mesh, so on a featureless surface noise is
amplified: a plate with ``1e-12`` of noise gets points.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch
from torch import Tensor

from ._common.checks import (
    check_bool,
    check_choice,
    check_number,
    check_optional_int,
    refuse_unused,
)
from ._common.errors import ParameterError
from ._common.variants import DEFAULT_RADIUS, DEFAULT_T_GLOBAL
from .mesh import as_mesh_tensors, check_batch
from .mesh.geometry import edge_graph, edge_uses

__all__ = [
    "DEFAULT_RADIUS",
    "DEFAULT_T_GLOBAL",
    "INTEREST_MODES",
    "InterestPointWarning",
    "boundary_vertices",
    "check_interest_parameters",
    "interest_points",
]

INTEREST_MODES = ("nms", "paper")


class InterestPointWarning(UserWarning):
    """Fewer interest points than ``top_k`` asked for; the message says why and what to try."""


def boundary_vertices(faces: Tensor, num_vertices: int) -> Tensor:
    """``(V,)`` bool: the vertices of a boundary edge, an edge that exactly one of the
    ``(F, 3)`` int64 ``faces`` uses (the rims of holes and cuts)."""
    return _rims(*edge_uses(faces, num_vertices), num_vertices)


def _rims(edges: Tensor, uses: Tensor, num_vertices: int) -> Tensor:
    """``(V,)`` bool: the vertices of the ``(E, 2)`` edges that ``uses`` says one face uses."""
    mask = torch.zeros(num_vertices, dtype=torch.bool, device=edges.device)
    mask[edges[uses == 1].reshape(-1)] = True
    return mask


def _candidates(saliency: Tensor, edges: Tensor, t_global: float, eligible: Tensor) -> Tensor:
    """Paper-mode points among the ``(V,)`` bool ``eligible`` vertices, most salient first
    (ties broken by vertex index); none where the saliency is the same on every vertex of the
    surface (nothing stands out)."""
    on_surface = torch.zeros_like(saliency, dtype=torch.bool)
    on_surface[edges.reshape(-1)] = True
    low, high = saliency[on_surface].min(), saliency[on_surface].max()
    if not bool(high > low):
        return edges.new_zeros(0)
    neighbour_max = saliency.new_full(saliency.shape, -torch.inf)  # over the 1-ring
    neighbour_max.scatter_reduce_(0, edges[:, 0], saliency[edges[:, 1]], reduce="amax")
    neighbour_max.scatter_reduce_(0, edges[:, 1], saliency[edges[:, 0]], reduce="amax")
    maxima = (saliency >= neighbour_max) & torch.isfinite(neighbour_max) & eligible
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
    include_boundary: bool = False,
) -> Tensor:
    """Interest points of a saliency field, most salient first.

    Args:
        saliency: ``(V,)`` float saliency, e.g. from
            :func:`~stochlap_torch.saliency_maps.mesh_saliency`.
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        mode: ``"nms"`` (default) or ``"paper"``, see the module docstring.
        radius: suppression radius for ``"nms"``, as a fraction of the bounding-box diagonal
            of the referenced vertices (default 0.1, :data:`DEFAULT_RADIUS`; ``"paper"`` refuses
            it).
        top_k: keep at most this many points (``None``: no cap); fewer found is an
            :class:`InterestPointWarning`.
        t_global: fraction of the saliency range a point must reach (0.4 in the paper).
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch (``None``: one
            mesh): points are found in each mesh on its own (``top_k`` per mesh), mesh by mesh.
        include_boundary: let vertices of boundary edges (:func:`boundary_vertices`) be
            interest points (default ``False``: the rims of holes are not).

    Returns:
        ``(N,)`` int64 vertex indices on the device of ``saliency``; empty for a mesh whose
        saliency is the same on every vertex (see the module docstring).
    """
    mode, radius, top_k, t_global = check_interest_parameters(mode, radius, top_k, t_global)
    include_boundary = check_bool("include_boundary", include_boundary)
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
    options = (mode, radius, top_k, t_global, include_boundary)
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
            chosen = _mesh_points(
                saliency[members], vertices[members], mesh_faces, *options, mesh=mesh
            )
            found.append(members[chosen])
    return torch.cat(found) if found else faces.new_zeros(0)


def _mesh_points(
    saliency, vertices, faces, mode, radius, top_k, t_global, include_boundary, mesh=None
) -> Tensor:
    """Interest points of one mesh (:func:`interest_points`, of validated tensors)."""
    num_vertices = vertices.shape[0]
    edges, uses = edge_uses(faces, num_vertices)
    eligible = torch.ones(num_vertices, dtype=torch.bool, device=saliency.device)
    if not include_boundary:
        eligible = ~_rims(edges, uses, num_vertices)
    candidates = _candidates(saliency, edges, t_global, eligible)
    if mode == "paper":
        kept = candidates[:top_k].tolist()
    else:
        points = vertices.detach().cpu().double().numpy()
        edge_array = edges.cpu().numpy()
        on_surface = np.unique(edge_array)
        extent = points[on_surface].max(axis=0) - points[on_surface].min(axis=0)
        diagonal = float(np.linalg.norm(extent))
        graph = edge_graph(points, edge_array)
        kept = _suppress(graph, candidates.tolist(), radius * diagonal, top_k)
    if top_k is not None and len(kept) < top_k:
        found = f"top_k={top_k} asked for, {len(kept)} interest points found"
        if mesh is not None:
            found += f" in mesh {mesh}"
        values = saliency[edges]
        if bool(values.amax() == values.amin()):
            why = "the saliency is the same on every vertex: nothing stands out"
        elif candidates.numel() < top_k:
            why = (
                f"only {candidates.numel()} local maxima of the saliency reach "
                f"t_global={t_global:g} (a lower t_global admits more)"
            )
        else:
            advice = _radius_for(graph, candidates, radius, diagonal, top_k)
            why = (
                f"the suppression radius {radius:g} leaves no room for more among "
                f"{candidates.numel()} local maxima ({advice})"
            )
        warnings.warn(f"{found}: {why}", InterestPointWarning, stacklevel=3)
    return torch.tensor(kept, dtype=torch.int64, device=saliency.device)


def _radius_for(graph, candidates: Tensor, radius: float, diagonal: float, top_k: int) -> str:
    """The suppression radius, halved until it leaves room for ``top_k`` points, as advice."""
    for halvings in range(1, 11):
        smaller = radius / 2**halvings
        if len(_suppress(graph, candidates.tolist(), smaller * diagonal, top_k)) == top_k:
            return f"radius={smaller:g} gives {top_k}"
    return "mode='paper' keeps every one of them"


def _suppress(graph, candidates: list[int], reach: float, top_k: int | None) -> list[int]:
    """Greedy non-maximum suppression: each candidate (most salient first) kept unless a kept
    one lies within graph-geodesic distance ``reach``; stops at ``top_k``."""
    from scipy.sparse.csgraph import dijkstra

    suppressed = np.zeros(graph.shape[0], dtype=bool)
    kept: list[int] = []
    for vertex in candidates:
        if top_k is not None and len(kept) >= top_k:
            break
        if suppressed[vertex]:
            continue
        kept.append(vertex)
        # The ball of radius ``reach``: Dijkstra stopped at that distance.
        suppressed[np.isfinite(dijkstra(graph, indices=vertex, limit=reach))] = True
    return kept

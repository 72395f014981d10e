"""Geodesic distances on a triangle mesh, from a set of source vertices.

* ``"heat"``: the heat method (Crane et al. 2013) of potpourri3d (the ``evaluation`` extra):
  one factorisation, then one solve per source.
* ``"dijkstra"``: shortest paths along the edges; they over-estimate surface distances in
  directions that follow no edge, but any mesh is accepted.
* ``"auto"``: the heat method when potpourri3d is installed and the mesh has no non-manifold
  edge (where it is silently wrong), else Dijkstra with a :class:`GeodesicFallbackWarning`.

potpourri3d gets the mesh compacted to its referenced vertices (it rejects or drops the
others); its finite values on components without the source are set to ``inf``. Unreferenced
vertices are at distance ``inf`` from all but themselves.
"""

from __future__ import annotations

import importlib
import warnings
from dataclasses import dataclass

import numpy as np
import torch
from scipy.sparse import csgraph
from torch import Tensor

from .._common.checks import check_choice
from .._common.errors import MissingDependencyError, ParameterError
from ..mesh import as_mesh_tensors, unique_edges
from ..mesh.geometry import edge_graph, edge_uses
from .constants import GEODESIC_METHODS

_EVALUATION_HINT = 'pip install "stochlap_torch[evaluation]"'
_DIJKSTRA_NOTE = (
    "geodesic distances by graph Dijkstra along the mesh edges instead of the heat method "
    "(edge paths are up to about 8 % longer, which changes the results)"
)


class GeodesicFallbackWarning(UserWarning):
    """``method="auto"`` fell back from the heat method to Dijkstra."""


@dataclass(frozen=True)
class GeodesicDistances:
    """Distances from source vertices to every vertex.

    Attributes:
        distances: ``(S, V)`` float64, ``distances[s, v]`` from ``sources[s]`` to ``v``;
            ``inf`` where ``v`` is not reachable (another component, unreferenced vertex).
        sources: ``(S,)`` int64 source vertex indices.
        method: ``"heat"`` or ``"dijkstra"``, the method that produced them.
    """

    distances: Tensor
    sources: Tensor
    method: str


def _potpourri3d():
    """The potpourri3d module, or ``None`` (tests replace this to simulate its absence)."""
    try:
        return importlib.import_module("potpourri3d")
    except ImportError:
        return None


def nonmanifold_edges(faces) -> Tensor:
    """Undirected edges shared by three or more faces.

    Args:
        faces: ``(F, 3)`` integer tensor or array.

    Returns:
        ``(N, 2)`` int64, ``i < j``, sorted.
    """
    faces = torch.as_tensor(faces, dtype=torch.int64)
    if faces.numel() == 0:
        return faces.new_zeros(0, 2)
    edges, uses = edge_uses(faces)
    return edges[uses > 2]


class _Solver:
    """Distances on one validated mesh by ``method`` (``"heat"`` or ``"dijkstra"``), with the
    set-up (edge graph, components, the heat method's factorisation) done once."""

    def __init__(self, vertices: Tensor, faces: Tensor, method: str, t_coef: float = 1.0):
        points = vertices.detach().cpu().double().numpy()
        self.num_vertices = points.shape[0]
        self.graph = edge_graph(points, unique_edges(faces.cpu(), self.num_vertices).numpy())
        _, self.labels = csgraph.connected_components(self.graph, directed=False)
        faces = faces.cpu().numpy()
        self.used = np.unique(faces)
        self.compact = np.full(self.num_vertices, -1, dtype=np.int64)
        self.compact[self.used] = np.arange(self.used.shape[0])
        self.heat = None
        if method == "heat":
            self.heat = _potpourri3d().MeshHeatMethodDistanceSolver(
                np.ascontiguousarray(points[self.used]),
                np.ascontiguousarray(self.compact[faces]),
                t_coef=t_coef,
            )

    def distances(self, sources: np.ndarray) -> np.ndarray:
        """``(S, V)`` float64 distances from ``sources``; ``inf`` when unreachable."""
        if self.heat is None:
            return np.atleast_2d(csgraph.dijkstra(self.graph, directed=False, indices=sources))
        out = np.full((sources.shape[0], self.num_vertices), np.inf)
        for row, source in enumerate(sources.tolist()):
            out[row, source] = 0.0
            if self.compact[source] < 0:
                continue
            distance = np.asarray(self.heat.compute_distance(int(self.compact[source])))
            out[row, self.used] = np.maximum(distance, 0.0)
            out[row, self.labels != self.labels[source]] = np.inf
            out[row, source] = 0.0
        return out


def choose_geodesic_method(faces, method: str = "auto") -> str:
    """The method :func:`geodesic_distances` uses for ``method`` on these faces (resolved
    once, ``"auto"`` warns once per mesh, not once per call).

    Args:
        faces: ``(F, 3)`` integer tensor or array.
        method: one of :data:`GEODESIC_METHODS`.

    Returns:
        ``"heat"`` or ``"dijkstra"``; :class:`MissingDependencyError` for ``"heat"`` without
        potpourri3d, a :class:`GeodesicFallbackWarning` when ``"auto"`` falls back to Dijkstra.
    """
    check_choice("method", method, GEODESIC_METHODS)
    if method == "dijkstra":
        return method
    if _potpourri3d() is None:
        if method == "heat":
            raise MissingDependencyError(
                "method='heat' needs potpourri3d, which is not installed; install it with: "
                f"{_EVALUATION_HINT}"
            )
        reason = f"potpourri3d is not installed ({_EVALUATION_HINT})"
    elif method == "heat" or not (bad := nonmanifold_edges(faces)).shape[0]:
        return "heat"
    else:
        reason = f"the mesh has {bad.shape[0]} non-manifold edges (e.g. {bad[0].tolist()})"
    warnings.warn(f"{reason}: {_DIJKSTRA_NOTE}", GeodesicFallbackWarning, stacklevel=2)
    return "dijkstra"


def geodesic_distances(
    vertices, faces, sources, method: str = "auto", t_coef: float = 1.0
) -> GeodesicDistances:
    """Geodesic distances from each source vertex to every vertex.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        sources: ``(S,)`` vertex indices (int, sequence or tensor).
        method: one of :data:`GEODESIC_METHODS` (module docstring).
        t_coef: time step of the heat method, in units of the squared mean edge length.

    Returns:
        :class:`GeodesicDistances` with ``(S, V)`` float64 distances.
    """
    vertices, faces = as_mesh_tensors(vertices, faces)
    sources = torch.as_tensor(sources, dtype=torch.int64).reshape(-1)
    num_vertices = vertices.shape[0]
    if sources.numel() == 0:
        raise ParameterError("sources is empty")
    if bool(((sources < 0) | (sources >= num_vertices)).any()):
        raise ParameterError(
            f"source indices must lie in [0, {num_vertices}), got {sources.tolist()}"
        )
    used = choose_geodesic_method(faces, method)
    distances = _Solver(vertices, faces, used, t_coef).distances(sources.cpu().numpy())
    return GeodesicDistances(torch.from_numpy(distances), sources, used)


def mesh_diameter(vertices, faces, method: str = "auto", sweeps: int = 4) -> float:
    """Geodesic diameter by farthest-point sweeps: in each component, from its first
    referenced vertex, each sweep moves to the vertex farthest from the current one. The
    largest distance seen is a lower bound, exact on a sphere or a flat patch.

    Args:
        vertices, faces: the mesh, ``(V, 3)`` float and ``(F, 3)`` integer tensors.
        method: as in :func:`geodesic_distances`.
        sweeps: farthest-point moves per component (``>= 1``).

    Returns:
        The diameter, in the units of ``vertices``.
    """
    if sweeps < 1:
        raise ParameterError(f"sweeps must be >= 1, got {sweeps}")
    vertices, faces = as_mesh_tensors(vertices, faces)
    solver = _Solver(vertices, faces, choose_geodesic_method(faces, method))
    _, first = np.unique(solver.labels[solver.used], return_index=True)
    best = 0.0
    for source in solver.used[first].tolist():
        for _ in range(sweeps):
            row = solver.distances(np.array([source]))[0]
            row = np.where(np.isfinite(row), row, -1.0)
            source = int(np.argmax(row))
            best = max(best, float(row[source]))
    return best

"""A pyramid of coarser copies of a mesh, for reaching large diffusion times at linear cost.

Level 0 is the mesh; each next level is a quadric decimation (fast-simplification) of every
connected component of the previous one to about ``1/ratio`` of its vertices. Every coarse
vertex is snapped to its nearest vertex of the level above, so the vertices of every level
are a subset of the mesh's vertices (:attr:`Level.vertex_ids`): a level's positions are a
gather of the fine positions, and gradients reach them. Values on a level come back to the
level above by barycentric interpolation on the closest coarse triangle (:attr:`Level.prolong`,
the triangles and weights chosen when the pyramid is built and then held fixed).
"""

from __future__ import annotations

import os
import threading
from dataclasses import dataclass

import numpy as np

from .. import _kernels
from .._common.errors import MeshError, MissingDependencyError
from ..mesh import connected_components, face_areas

__all__ = ["Level", "build_pyramid"]

#: Components with fewer vertices than this are carried to the next level unchanged.
_MIN_COMPONENT = 128
#: Candidate coarse vertices per fine point when looking for its closest coarse triangle.
_CANDIDATES = 4

#: fast-simplification keeps the mesh being decimated in C++ globals, filled and read back by
#: separate calls between which Python may switch threads: one decimation at a time.
_DECIMATION_LOCK = threading.Lock()


def _new_decimation_lock() -> None:
    global _DECIMATION_LOCK
    _DECIMATION_LOCK = threading.Lock()  # a fork child owns no thread that could hold it


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_new_decimation_lock)


@dataclass
class Level:
    """One level of a :func:`build_pyramid`.

    Attributes:
        vertices: ``(n, 3)`` float64 positions.
        faces: ``(m, 3)`` int64 triangles.
        vertex_ids: ``(n,)`` int64 index of every vertex in level 0.
        labels: ``(n,)`` int64 connected component of every vertex.
        prolong: ``(face, bary)``: for every vertex of the level above, the triangle of this
            level closest to it (``(n_above,)``) and the barycentric coordinates of the closest
            point (``(n_above, 3)``); ``None`` on level 0.
        deviation: a bound on the distance of the mesh's surface to this level's (sum over the
            levels above of the 95th percentile of the closest-point distances).
        mean_vertex_area: total area over the vertex count.
    """

    vertices: np.ndarray
    faces: np.ndarray
    vertex_ids: np.ndarray
    labels: np.ndarray
    prolong: tuple[np.ndarray, np.ndarray] | None
    deviation: float
    mean_vertex_area: float


#: The error of a mesh whose parts differ in size by more than float32 holds (a vertex 1e100
#: away from the others: at unit area, the rest of the mesh is far below float32's range).
_SPAN_MESSAGE = (
    "the mesh's triangles differ in size by more than the robust variant can represent "
    "(its decimation works in float32): some vertices lie orders of magnitude farther out "
    "than the rest; remove them, or use variant='paper'"
)


def _unstacked(triangles: np.ndarray) -> np.ndarray:
    """``(m,)`` bool: the triangles no other triangle shares its three vertices with.

    Snapping can stack two triangles on the same three vertices (a collapsed fold): both
    copies go, which leaves the other triangles at their edges a closed surface. (A lexical
    sort of the rows: ``np.unique(axis=0)`` took three times as long.)
    """
    rows = np.sort(triangles, axis=1)
    order = np.lexsort(rows.T[::-1])
    rows = rows[order]
    same = np.all(rows[1:] == rows[:-1], axis=1)
    stacked = np.zeros(rows.shape[0], dtype=bool)
    stacked[1:] |= same
    stacked[:-1] |= same
    keep = np.empty(rows.shape[0], dtype=bool)
    keep[order] = ~stacked
    return keep


def _decimate_component(vertices, faces, ratio: float, threads: int):
    """Quadric decimation of one component to about ``1/ratio`` of its vertices, snapped to
    its own vertices: ``(kept, faces)`` (indices into ``vertices``)."""
    try:
        import fast_simplification
    except ImportError as error:  # pragma: no cover - a dependency of the package
        raise MissingDependencyError(
            "the robust variant needs fast-simplification: pip install fast-simplification"
        ) from error
    from scipy.spatial import cKDTree

    target = max(int(vertices.shape[0] / ratio), 4)
    with np.errstate(over="ignore"):  # checked on the next line
        single = vertices.astype(np.float32)  # fast-simplification works in float32
    if not np.isfinite(single).all():
        raise MeshError(_SPAN_MESSAGE)
    with _DECIMATION_LOCK:
        points, triangles = fast_simplification.simplify(
            single,
            faces.astype(np.int32),
            target_reduction=1.0 - target / vertices.shape[0],
        )
    _, snapped = cKDTree(vertices).query(np.asarray(points, dtype=np.float64), workers=threads)
    triangles = np.asarray(snapped, dtype=np.int64)[np.asarray(triangles, dtype=np.int64)]
    keep = (
        (triangles[:, 0] != triangles[:, 1])
        & (triangles[:, 1] != triangles[:, 2])
        & (triangles[:, 2] != triangles[:, 0])
    )
    triangles = triangles[keep]
    triangles = triangles[_unstacked(triangles)]
    kept = np.unique(triangles)
    if kept.size < 4:  # decimation destroyed the component: keep it whole
        return np.arange(vertices.shape[0]), faces
    return kept, triangles


def _coarser(level: Level, ratio: float, threads: int) -> tuple[np.ndarray, np.ndarray]:
    """``(parent, faces)`` of the next level: the kept vertices of ``level`` (indices into it)
    and the coarse triangles in the coarse numbering; component by component."""
    parents, triangles, offset = [], [], 0
    for label in np.unique(level.labels):
        members = np.flatnonzero(level.labels == label)
        local = np.full(level.vertices.shape[0], -1, dtype=np.int64)
        local[members] = np.arange(members.size)
        component_faces = local[level.faces[level.labels[level.faces[:, 0]] == label]]
        if members.size >= _MIN_COMPONENT and component_faces.shape[0]:
            kept, faces = _decimate_component(
                level.vertices[members], component_faces, ratio, threads
            )
        else:
            kept, faces = np.arange(members.size), component_faces
        remap = np.full(members.size, -1, dtype=np.int64)
        remap[kept] = np.arange(kept.size) + offset
        parents.append(members[kept])
        triangles.append(remap[faces])
        offset += kept.size
    return np.concatenate(parents), np.concatenate(triangles)


def _prolongation(fine: Level, vertices, faces, labels, threads: int):
    """Closest coarse triangle of every fine vertex (candidates: the coarse vertices of its
    own component nearest to it), and the 95th percentile of the distances."""
    from scipy.spatial import cKDTree

    count = fine.vertices.shape[0]
    near = np.empty((count, _CANDIDATES), dtype=np.int64)
    for label in np.unique(fine.labels):
        points = np.flatnonzero(fine.labels == label)
        coarse = np.flatnonzero(labels == label)
        k = min(_CANDIDATES, coarse.size)
        _, index = cKDTree(vertices[coarse]).query(fine.vertices[points], k=k, workers=threads)
        index = coarse[np.asarray(index).reshape(points.size, k)]
        near[points] = np.concatenate([index, np.repeat(index[:, :1], _CANDIDATES - k, 1)], 1)
    face, bary = _kernels.closest_triangles(fine.vertices, vertices, faces, near, threads)
    closest = np.einsum("ij,ijc->ic", bary, vertices[faces[face]])
    distance = np.linalg.norm(closest - fine.vertices, axis=1)
    return (face, bary), float(np.percentile(distance, 95)) if count else 0.0


def _mean_vertex_area(vertices: np.ndarray, faces: np.ndarray) -> float:
    import torch

    area = float(face_areas(torch.from_numpy(vertices), torch.from_numpy(faces)).sum())
    return area / max(vertices.shape[0], 1)


def build_pyramid(
    vertices: np.ndarray,
    faces: np.ndarray,
    ratio: float = 4.0,
    min_vertices: int = 1000,
    threads: int = 1,
) -> list[Level]:
    """Level 0 (the mesh) and coarser levels, each about ``ratio`` times smaller, until the
    next would have fewer than about ``min_vertices`` vertices or decimation stalls.

    Args:
        vertices: ``(V, 3)`` float64, every vertex referenced by a face.
        faces: ``(F, 3)`` int64.
        ratio: vertex-count ratio between levels.
        min_vertices: size below which no coarser level is built.
        threads: threads for the nearest-vertex and closest-triangle queries (scipy's k-d
            tree starts its own for a call and joins them before returning).
    """
    labels = connected_components(
        vertices.shape[0], np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    )
    levels = [
        Level(
            vertices,
            faces,
            np.arange(vertices.shape[0]),
            labels,
            None,
            0.0,
            _mean_vertex_area(vertices, faces),
        )
    ]
    while levels[-1].vertices.shape[0] > min_vertices * ratio / 2:
        above = levels[-1]
        parent, coarse_faces = _coarser(above, ratio, threads)
        if parent.size > 0.8 * above.vertices.shape[0]:
            break
        coarse_vertices = above.vertices[parent]
        coarse_labels = above.labels[parent]
        prolong, distance = _prolongation(
            above, coarse_vertices, coarse_faces, coarse_labels, threads
        )
        levels.append(
            Level(
                coarse_vertices,
                coarse_faces,
                above.vertex_ids[parent],
                coarse_labels,
                prolong,
                above.deviation + distance,
                _mean_vertex_area(coarse_vertices, coarse_faces),
            )
        )
    return levels

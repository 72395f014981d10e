"""Large meshes are drawn from a decimated copy: a panel shows no more than about
:data:`DRAW_FACES` triangles, and matplotlib's time goes with their count. Above that budget
the faces are a quadric decimation (fast-simplification) snapped to the original vertices, so
per-vertex values, interest points and the other scales of a representation carry over."""

from __future__ import annotations

import numpy as np

from ._arrays import used_vertices

#: The default face budget of a picture: meshes with more faces are drawn decimated.
DRAW_FACES = 100_000


def _without_repeats(triangles: np.ndarray) -> np.ndarray:
    """``(m, 3)`` triangles minus those with a repeated corner and those stacked on the same
    three vertices as another (a fold that snapping collapsed: both copies go, so that the
    triangles around it still close the surface)."""
    a, b, c = triangles.T
    triangles = triangles[(a != b) & (b != c) & (c != a)]
    rows = np.sort(triangles, axis=1)
    order = np.lexsort(rows.T[::-1])
    same = np.all(rows[order][1:] == rows[order][:-1], axis=1)
    stacked = np.zeros(rows.shape[0], dtype=bool)
    stacked[1:] |= same
    stacked[:-1] |= same
    keep = np.empty(rows.shape[0], dtype=bool)
    keep[order] = ~stacked
    return triangles[keep]


def drawing_faces(vertices: np.ndarray, faces: np.ndarray, max_faces: int | None) -> np.ndarray:
    """The ``(F', 3)`` int64 faces to draw: ``faces`` within the budget ``max_faces``
    (``None``: no budget), else about ``max_faces`` snapped triangles (module docstring)."""
    if max_faces is None or faces.shape[0] <= max_faces:
        return faces
    import fast_simplification
    from scipy.spatial import cKDTree

    points, triangles = fast_simplification.simplify(
        vertices, faces.astype(np.int32), target_count=max_faces
    )
    # Snapped to vertices some face uses, never to a stray one.
    used = used_vertices(faces, vertices.shape[0])
    _, nearest = cKDTree(vertices[used]).query(np.asarray(points, dtype=np.float64))
    snapped = used[np.asarray(nearest, dtype=np.int64)][np.asarray(triangles, dtype=np.int64)]
    drawn = _without_repeats(snapped)
    return drawn if drawn.shape[0] else faces


def nearest_drawn(vertices: np.ndarray, drawn: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(N,)`` indices of the vertices the ``(F', 3)`` drawn faces use nearest to the ``(N,)``
    vertex indices ``points`` (a point the decimation dropped is marked on the surface drawn,
    not under it)."""
    if points.size == 0:
        return points
    from scipy.spatial import cKDTree

    used = used_vertices(drawn, vertices.shape[0])
    _, nearest = cKDTree(vertices[used]).query(vertices[points])
    return used[np.asarray(nearest, dtype=np.int64)]

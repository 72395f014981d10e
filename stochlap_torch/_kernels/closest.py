"""Closest points on a triangle mesh, for prolonging values from a coarse mesh to a fine one.

For every query point, the candidate triangles are those around its few nearest coarse
vertices (a k-d tree gives those); the kernel returns the closest triangle and the barycentric
coordinates of the closest point on it. Hand-written because no well-kept package answers this
in linear time for millions of points; it runs on the thread driver (:mod:`.threads`).
"""

from __future__ import annotations

import numpy as np

from ._numba import numba_available
from .jit import kernel_jit
from .threads import kernel_thread_count, run_workers

if numba_available():
    from numba import njit

    from .threads import next_part

__all__ = ["closest_triangles"]

#: Query points per unit of work handed to a thread.
_CHUNK = 1024


if numba_available():

    @njit(nogil=True, inline="always")
    def _dot(ax, ay, az, bx, by, bz):  # pragma: no cover - compiled
        return ax * bx + ay * by + az * bz

    @njit(nogil=True)
    def _closest_on_triangle(p, a, b, c):  # pragma: no cover - compiled
        """Barycentric ``(u, v, w)`` of the point of triangle ``abc`` closest to ``p`` and its
        squared distance (Ericson, Real-Time Collision Detection, 5.1.5)."""
        abx, aby, abz = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        acx, acy, acz = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        d1 = _dot(abx, aby, abz, p[0] - a[0], p[1] - a[1], p[2] - a[2])
        d2 = _dot(acx, acy, acz, p[0] - a[0], p[1] - a[1], p[2] - a[2])
        d3 = _dot(abx, aby, abz, p[0] - b[0], p[1] - b[1], p[2] - b[2])
        d4 = _dot(acx, acy, acz, p[0] - b[0], p[1] - b[1], p[2] - b[2])
        d5 = _dot(abx, aby, abz, p[0] - c[0], p[1] - c[1], p[2] - c[2])
        d6 = _dot(acx, acy, acz, p[0] - c[0], p[1] - c[1], p[2] - c[2])
        vc = d1 * d4 - d3 * d2
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d1 <= 0.0 and d2 <= 0.0:
            u, v, w = 1.0, 0.0, 0.0
        elif d3 >= 0.0 and d4 <= d3:
            u, v, w = 0.0, 1.0, 0.0
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            s = d1 / (d1 - d3)
            u, v, w = 1.0 - s, s, 0.0
        elif d6 >= 0.0 and d5 <= d6:
            u, v, w = 0.0, 0.0, 1.0
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            s = d2 / (d2 - d6)
            u, v, w = 1.0 - s, 0.0, s
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            s = (d4 - d3) / ((d4 - d3) + (d5 - d6))
            u, v, w = 0.0, 1.0 - s, s
        else:
            den = va + vb + vc
            if den <= 0.0:  # a degenerate triangle: its first corner
                u, v, w = 1.0, 0.0, 0.0
            else:
                v, w = vb / den, vc / den
                u = 1.0 - v - w
        qx = u * a[0] + v * b[0] + w * c[0] - p[0]
        qy = u * a[1] + v * b[1] + w * c[1] - p[1]
        qz = u * a[2] + v * b[2] + w * c[2] - p[2]
        return u, v, w, qx * qx + qy * qy + qz * qz

    @njit(nogil=True, inline="always")
    def _seen(face, faces, near, q, k):  # pragma: no cover - compiled
        """Whether ``face`` was tested for an earlier candidate than the ``k``-th (it lies
        around it too): neighbouring candidates share most of their triangles, and the first
        test of a triangle is the one that counts (a later equal distance never wins)."""
        for earlier in range(k):
            corner = near[q, earlier]
            if faces[face, 0] == corner or faces[face, 1] == corner or faces[face, 2] == corner:
                return True
        return False

    @kernel_jit(nogil=True)
    def _closest_worker(
        thread, counter, points, vertices, faces, near, vf_ptr, vf_idx, out_face, out_bary
    ):  # pragma: no cover - compiled
        """Closest triangle and barycentric coordinates of the query points, in chunks of
        :data:`_CHUNK` taken from ``counter``."""
        count = points.shape[0]
        while True:
            first = next_part(counter) * _CHUNK
            if first >= count:
                break
            for q in range(first, min(first + _CHUNK, count)):
                best = np.inf
                for k in range(near.shape[1]):
                    corner = near[q, k]
                    for s in range(vf_ptr[corner], vf_ptr[corner + 1]):
                        face = vf_idx[s]
                        if _seen(face, faces, near, q, k):
                            continue
                        u, v, w, d2 = _closest_on_triangle(
                            points[q],
                            vertices[faces[face, 0]],
                            vertices[faces[face, 1]],
                            vertices[faces[face, 2]],
                        )
                        if d2 < best:
                            best = d2
                            out_face[q] = face
                            out_bary[q, 0], out_bary[q, 1], out_bary[q, 2] = u, v, w


def closest_triangles(
    points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, near: np.ndarray, threads: int
) -> tuple[np.ndarray, np.ndarray]:
    """For every query point, the closest triangle among those around its candidate vertices.

    Args:
        points: ``(N, 3)`` float64 query points.
        vertices, faces: the mesh, ``(n, 3)`` float64 and ``(m, 3)`` int64.
        near: ``(N, k)`` int64 candidate vertices of every point (e.g. its k nearest).
        threads: threads to use.

    Returns:
        ``(face, bary)``: ``(N,)`` int64 closest triangle and ``(N, 3)`` float64 barycentric
        coordinates of the closest point on it.
    """
    num_vertices = vertices.shape[0]
    order = np.argsort(faces.reshape(-1), kind="stable")
    vf_idx = (order // 3).astype(np.int64)
    vf_ptr = np.zeros(num_vertices + 1, dtype=np.int64)
    np.cumsum(np.bincount(faces.reshape(-1), minlength=num_vertices), out=vf_ptr[1:])
    face = np.zeros(points.shape[0], dtype=np.int64)
    bary = np.zeros((points.shape[0], 3))
    bary[:, 0] = 1.0
    chunks = -(-points.shape[0] // _CHUNK)
    run_workers(
        _closest_worker,
        kernel_thread_count(threads, chunks),
        np.zeros(1, dtype=np.int64),
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64),
        np.ascontiguousarray(near, dtype=np.int64),
        vf_ptr,
        vf_idx,
        face,
        bary,
    )
    return face, bary

"""Shading and visibility of a mesh in its drawing frame (numpy only).

Two-sided Lambert shading from a light above and left of the camera: per vertex (smooth) when
the faces are consistently oriented, per face otherwise; back faces culled when the mesh is
closed.
"""

from __future__ import annotations

import numpy as np

from .framing import direction

#: The share of light every face gets whatever its normal.
_AMBIENT = 0.28


def unit_rows(vectors: np.ndarray) -> np.ndarray:
    """``(N, 3)`` rows scaled to unit length (zero rows stay zero)."""
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, norms, out=np.zeros_like(vectors), where=norms > 0)


class Geometry:
    """What shading needs of ``(V, 3)`` ``frame`` positions and ``(F, 3)`` int64 ``faces``,
    computed once for all views: ``face_normals`` (unit, zero for degenerate faces),
    ``vertex_normals`` (area-weighted, ``None`` when the faces are not consistently oriented)
    and ``outward`` (+1 or -1 for a closed, consistently oriented mesh, whose back faces are
    culled; else 0)."""

    def __init__(self, frame: np.ndarray, faces: np.ndarray):
        a, b, c = (frame[faces[:, i]] for i in range(3))
        area_normals = np.cross(b - a, c - a)
        self.face_normals = unit_rows(area_normals)
        self.vertex_normals = None
        self.outward = 0.0
        directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        num_vertices = int(frame.shape[0])
        keys = np.sort(directed[:, 0] * num_vertices + directed[:, 1])
        # A directed edge used twice means two neighbouring faces disagree on orientation.
        if (keys[1:] == keys[:-1]).any():
            return
        summed = np.zeros_like(frame)
        for i in range(3):
            np.add.at(summed, faces[:, i], area_normals)
        self.vertex_normals = unit_rows(summed)
        reverse = directed[:, 1] * num_vertices + directed[:, 0]
        found = np.minimum(np.searchsorted(keys, reverse), keys.size - 1)
        if (keys[found] == reverse).all():  # no boundary edge: closed
            volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum())
            self.outward = float(np.sign(volume))

    def front_faces(self, elev: float, azim: float) -> np.ndarray:
        """Indices of the faces drawn from ``(elev, azim)``: all, or the front ones when the
        mesh is closed and consistently oriented."""
        if self.outward == 0.0:
            return np.arange(self.face_normals.shape[0])
        facing = self.outward * (self.face_normals @ direction(elev, azim))
        return np.flatnonzero(facing > -1e-9)

    def shade(
        self, faces: np.ndarray, keep: np.ndarray, elev: float, azim: float, smooth: bool = True
    ) -> np.ndarray:
        """``(len(keep), 3)`` shading factors in ``[ambient, 1]`` of the corners of the faces
        ``keep`` seen from ``(elev, azim)``: per vertex when vertex normals exist and
        ``smooth`` (interpolated across each face when drawn), their mean over each face when
        not ``smooth`` (flat), per face without vertex normals."""
        light = direction(elev + 30.0, azim - 35.0)
        if self.vertex_normals is None:
            lambert = np.repeat(np.abs(self.face_normals[keep] @ light)[:, None], 3, axis=1)
        else:
            lambert = np.abs(self.vertex_normals @ light)[faces[keep]]
            if not smooth:
                lambert = np.repeat(lambert.mean(axis=1, keepdims=True), 3, axis=1)
        return _AMBIENT + (1.0 - _AMBIENT) * lambert


def visible_points(
    frame: np.ndarray, faces: np.ndarray, points: np.ndarray, towards: np.ndarray
) -> np.ndarray:
    """``(N,)`` bool: which ``(N, 3)`` points no triangle of ``frame``/``faces`` hides from a
    camera at infinity along the unit ``towards`` (Moller-Trumbore, chunks of faces)."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    scale = float(np.ptp(frame, axis=0).max()) or 1.0
    origins = points + 1e-4 * scale * towards
    a, b, c = (frame[faces[:, i]] for i in range(3))
    edge1, edge2 = b - a, c - a
    pvec = np.cross(towards, edge2)
    det = np.einsum("ij,ij->i", edge1, pvec)
    usable = np.abs(det) > 1e-14 * scale * scale
    edge1, edge2, a, pvec = edge1[usable], edge2[usable], a[usable], pvec[usable]
    inv_det = 1.0 / det[usable]
    hidden = np.zeros(points.shape[0], dtype=bool)
    chunk = max(1, 2_000_000 // max(1, a.shape[0]))
    for start in range(0, points.shape[0], chunk):
        tvec = origins[start : start + chunk, None, :] - a[None]  # (n, F, 3)
        u = np.einsum("nfi,fi->nf", tvec, pvec) * inv_det
        qvec = np.cross(tvec, edge1[None])
        v = np.einsum("i,nfi->nf", towards, qvec) * inv_det
        t = np.einsum("fi,nfi->nf", edge2, qvec) * inv_det
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        hidden[start : start + chunk] = hit.any(axis=1)
    return ~hidden

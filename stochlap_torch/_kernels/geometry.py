"""Geometry kernels of the robust variant's pyramid and heat operator.

* :func:`closest_triangles`: the closest triangle around a query point's nearest coarse
  vertices (no well-kept package answers this in linear time for millions of points).
* :func:`intrinsic_delaunay`: edge flips (Fisher et al. 2007) on lengths mollified as
  robust-laplacian does: on a closed, oriented, edge-manifold mesh its tufted cover is two
  copies of the mesh, so the result is its Laplacian; robust-laplacian (which holds the GIL)
  handles the other meshes. Halfedge ``3 f + c`` is corner ``c`` of face ``f``, from ``tail``
  to the tail of the next corner.
"""

from __future__ import annotations

import numpy as np

from .._common.errors import MissingDependencyError
from .jit import kernel_jit
from .threads import kernel_thread_count, numba_available, run_workers

if numba_available():
    from numba import njit

    from .threads import next_part

#: Query points per unit of work handed to a thread.
_CHUNK = 1024
#: robust-laplacian's default relative mollification.
MOLLIFY_FACTOR = 1e-5
#: An edge is flipped when its cotangent weight is below minus this (robust-laplacian's).
_DELAUNAY_EPS = 1e-6


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

    @njit(nogil=True, inline="always")
    def _area(a, b, c):  # pragma: no cover - compiled
        """Heron's formula, clamped at zero."""
        s = 0.5 * (a + b + c)
        value = s * (s - a) * (s - b) * (s - c)
        return np.sqrt(value) if value > 0.0 else 0.0

    @njit(nogil=True, inline="always")
    def _half_cot(opposite, b, c, area):  # pragma: no cover - compiled
        """Half the cotangent of the angle facing the side ``opposite`` (sides ``b``, ``c``)."""
        return (b * b + c * c - opposite * opposite) / (8.0 * area) if area > 0.0 else 0.0

    @njit(nogil=True)
    def _edge_weight(he, twin, edge, length):  # pragma: no cover - compiled
        """The cotangent weight of the edge of halfedge ``he`` (both of its triangles)."""
        total = 0.0
        for h in (he, twin[he]):
            base = h - h % 3
            a = length[edge[h]]
            b = length[edge[base + (h + 1) % 3]]
            c = length[edge[base + (h + 2) % 3]]
            total += _half_cot(a, b, c, _area(a, b, c))
        return total

    @njit(nogil=True)
    def _flipped_length(l_ij, l_jk, l_ki, l_ip, l_pj):  # pragma: no cover - compiled
        """``|k - p|`` with the triangles ``(i, j, k)`` and ``(j, i, p)`` laid out in the plane
        on either side of ``ij``."""
        xk = (l_ij * l_ij + l_ki * l_ki - l_jk * l_jk) / (2.0 * l_ij)
        yk = np.sqrt(max(l_ki * l_ki - xk * xk, 0.0))
        xp = (l_ij * l_ij + l_ip * l_ip - l_pj * l_pj) / (2.0 * l_ij)
        yp = -np.sqrt(max(l_ip * l_ip - xp * xp, 0.0))
        return np.sqrt((xk - xp) ** 2 + (yk - yp) ** 2)

    @njit(nogil=True, inline="always")
    def _moved(h, a1, a2, b1, b2, fa, fb):  # pragma: no cover - compiled
        """Where a flip of the quad ``a1 a2 | b1 b2`` puts halfedge ``h`` (the slots of
        :func:`_flip_to_delaunay`): ``h`` itself unless it is a side of the quad."""
        if h == b1:
            return fa
        if h == a2:
            return fa + 2
        if h == b2:
            return fb
        if h == a1:
            return fb + 1
        return h

    @kernel_jit(nogil=True)
    def _flip_to_delaunay(tail, twin, edge, length, max_flips):  # pragma: no cover - compiled
        """Flip, in place, until every edge's weight is at least ``-_DELAUNAY_EPS``; the number
        of flips, or ``-1`` if ``max_flips`` did not suffice or an edge stayed below (both its
        halfedges in one face: robust-laplacian answers for such a mesh). A flip may join a
        vertex to itself, as geometry-central's does: the triangulation is a Delta-complex."""
        num_edges = length.shape[0]
        edge_he = np.empty(num_edges, dtype=np.int64)
        for h in range(tail.shape[0]):
            edge_he[edge[h]] = h
        queue = np.arange(num_edges)
        queued = np.ones(num_edges, dtype=np.bool_)
        head, count, flips = 0, num_edges, 0
        while count > 0:
            e = queue[head]
            head = (head + 1) % num_edges
            count -= 1
            queued[e] = False
            a0 = edge_he[e]
            if _edge_weight(a0, twin, edge, length) >= -_DELAUNAY_EPS:
                continue
            fa, fb = a0 - a0 % 3, twin[a0] - twin[a0] % 3
            b0 = twin[a0]
            a1, a2 = fa + (a0 + 1) % 3, fa + (a0 + 2) % 3
            b1, b2 = fb + (b0 + 1) % 3, fb + (b0 + 2) % 3
            i, j, k, p = tail[a0], tail[a1], tail[a2], tail[b2]
            if fa == fb:
                continue  # an edge inside one face has no quad to flip in: leave it
            new = _flipped_length(
                length[e], length[edge[a1]], length[edge[a2]], length[edge[b1]], length[edge[b2]]
            )
            if not np.isfinite(new):
                continue
            flips += 1
            if flips > max_flips:
                return -1
            ea1, ea2, eb1, eb2 = edge[a1], edge[a2], edge[b1], edge[b2]
            # old outer halfedges' twins, where they will be: a side of the quad glued to
            # another (around a vertex of degree 2) moves with it
            ta1 = _moved(twin[a1], a1, a2, b1, b2, fa, fb)
            ta2 = _moved(twin[a2], a1, a2, b1, b2, fa, fb)
            tb1 = _moved(twin[b1], a1, a2, b1, b2, fa, fb)
            tb2 = _moved(twin[b2], a1, a2, b1, b2, fa, fb)
            # face A becomes (i, p, k), face B (p, j, k); e joins p and k
            slots = (
                (fa, i, eb1, tb1),
                (fa + 1, p, e, fb + 2),
                (fa + 2, k, ea2, ta2),
                (fb, p, eb2, tb2),
                (fb + 1, j, ea1, ta1),
                (fb + 2, k, e, fa + 1),
            )
            for h, vertex, which, other in slots:
                tail[h], edge[h], twin[h] = vertex, which, other
                twin[other] = h
                edge_he[which] = h
            length[e] = new
            for h in (fa, fa + 2, fb, fb + 1):  # the four outer edges may have turned bad
                outer = edge[h]
                if not queued[outer]:
                    queue[(head + count) % num_edges] = outer
                    count += 1
                    queued[outer] = True
        for e in range(num_edges):  # an edge left unflipped (inside one face)
            if _edge_weight(edge_he[e], twin, edge, length) < -_DELAUNAY_EPS:
                return -1
        return flips

    @kernel_jit(nogil=True)
    def _weights_and_mass(tail, edge, length, num_vertices):  # pragma: no cover
        """``(i, j, w)`` of every edge (from its first halfedge) and the lumped vertex areas."""
        num_edges = length.shape[0]
        rows = np.empty(num_edges, dtype=np.int64)
        cols = np.empty(num_edges, dtype=np.int64)
        weights = np.zeros(num_edges)
        seen = np.zeros(num_edges, dtype=np.bool_)
        mass = np.zeros(num_vertices)
        for f in range(tail.shape[0] // 3):
            base = 3 * f
            area = _area(length[edge[base]], length[edge[base + 1]], length[edge[base + 2]])
            for corner in range(3):
                h = base + corner
                mass[tail[h]] += area / 3.0
                b = length[edge[base + (corner + 1) % 3]]
                c = length[edge[base + (corner + 2) % 3]]
                weights[edge[h]] += _half_cot(length[edge[h]], b, c, area)
                if not seen[edge[h]]:
                    seen[edge[h]] = True
                    rows[edge[h]] = tail[h]
                    cols[edge[h]] = tail[base + (corner + 1) % 3]
        return rows, cols, weights, mass


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


def _halfedges(faces: np.ndarray, num_vertices: int):
    """``(tail, twin, edge, num_edges)`` of a closed, oriented, edge-manifold mesh, or ``None``
    for any other mesh."""
    tail = faces.reshape(-1)
    head = faces[:, [1, 2, 0]].reshape(-1)
    low, high = np.minimum(tail, head), np.maximum(tail, head)
    key = low * num_vertices + high
    order = np.argsort(key, kind="stable")
    if order.size % 2:
        return None
    first, second = order[0::2], order[1::2]
    # every undirected edge exactly twice, once in each direction
    if not np.array_equal(key[first], key[second]):
        return None
    if order.size > 2 and not (key[first][1:] > key[first][:-1]).all():
        return None
    if not np.array_equal(tail[first], head[second]):
        return None
    twin = np.empty(tail.size, dtype=np.int64)
    twin[first], twin[second] = second, first
    edge = np.empty(tail.size, dtype=np.int64)
    edge[first] = edge[second] = np.arange(first.size)
    return tail.astype(np.int64), twin, edge, int(first.size)


def intrinsic_delaunay(vertices: np.ndarray, faces: np.ndarray):
    """``(rows, cols, weights, mass)`` of the intrinsic Delaunay triangulation of ``(n, 3)``
    float64 ``vertices`` and ``(m, 3)`` int64 ``faces`` (every vertex referenced): ``(E,)``
    endpoints and cotangent weights of every edge (a pair may occur twice: an intrinsic
    triangulation can join two vertices by two edges, or a vertex to itself: a loop, whose
    weight the Laplacian ignores) and ``(n,)`` vertex areas; ``None``
    unless the mesh is closed, oriented and edge-manifold and the flips reach Delaunay."""
    triangulation = delaunay_triangulation(vertices, faces)
    if triangulation is None:
        return None
    tail, _, edge, length = triangulation
    return _weights_and_mass(tail, edge, length, vertices.shape[0])


def delaunay_triangulation(vertices: np.ndarray, faces: np.ndarray):
    """``(tail, twin, edge, length)`` of the intrinsic Delaunay triangulation
    (:func:`intrinsic_delaunay`), halfedge ``3 f + c`` being corner ``c`` of face ``f``:
    ``(3 m,)`` its tail vertex, its twin halfedge and its edge, and ``(E,)`` the edges'
    lengths; ``None`` where :func:`intrinsic_delaunay` is."""
    if not numba_available() or faces.shape[0] == 0:
        return None
    parts = _halfedges(np.ascontiguousarray(faces, dtype=np.int64), vertices.shape[0])
    if parts is None:
        return None
    tail, twin, edge, num_edges = parts
    head = tail.reshape(-1, 3)[:, [1, 2, 0]].reshape(-1)
    first = np.empty(num_edges, dtype=np.int64)
    first[edge] = np.arange(edge.size)
    length = np.linalg.norm(vertices[tail[first]] - vertices[head[first]], axis=1)
    # robust-laplacian's mollification: every triangle inequality holds by delta
    delta = MOLLIFY_FACTOR * float(length.mean())
    a, b, c = length[edge].reshape(-1, 3).T
    slack = max((a - b - c).max(), (b - c - a).max(), (c - a - b).max())
    length = length + max(0.0, float(slack) + delta)
    if _flip_to_delaunay(tail, twin, edge, length, 100 * num_edges + 1000) < 0:
        return None
    return tail, twin, edge, length


def intrinsic_delaunay_weights(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge weights and lumped areas of robust-laplacian's intrinsic Delaunay cotangent
    Laplacian of ``(n, 3)`` float64 ``vertices`` and ``(m, 3)`` int64 ``faces``, by
    :func:`intrinsic_delaunay` when it can (the same matrix to rounding).

    Returns:
        ``(edges (E, 2) int64 with i < j, weights (E,) float64 >= 0, mass (n,) float64)``: the
        edges of the intrinsic triangulation (which may join vertices no face joins), their
        weights ``W_ij = -L_ij`` (rounding below zero clamped) and the vertex areas.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces)
    flipped = intrinsic_delaunay(vertices, faces)
    if flipped is not None:
        rows, cols, weights, mass = flipped
    else:
        rows, cols, weights, mass = _robust_laplacian(vertices, faces)
    edge = rows != cols  # a loop moves nothing: x_i - x_i = 0
    rows, cols, weights = rows[edge], cols[edge], weights[edge]
    # One int64 key per vertex pair: one sort, not np.unique over rows.
    count = vertices.shape[0]
    keys = np.minimum(rows, cols).astype(np.int64) * count + np.maximum(rows, cols)
    pairs, inverse = np.unique(keys, return_inverse=True)
    summed = np.bincount(inverse.reshape(-1), weights=weights, minlength=pairs.size)
    edges = np.stack([pairs // count, pairs % count], axis=1)
    return edges, np.maximum(summed, 0.0), mass


def _robust_laplacian(vertices: np.ndarray, faces: np.ndarray):
    """``(rows, cols, weights, mass)`` from robust-laplacian (any mesh)."""
    try:
        import robust_laplacian
    except ImportError as error:  # pragma: no cover - a dependency of the package
        raise MissingDependencyError(
            "the robust variant needs robust-laplacian: pip install robust-laplacian"
        ) from error
    from scipy import sparse

    laplacian, mass = robust_laplacian.mesh_laplacian(vertices, faces)
    upper = sparse.triu(laplacian, k=1).tocoo()
    weights = -np.asarray(upper.data, dtype=np.float64)
    return upper.row, upper.col, weights, np.asarray(mass.diagonal(), dtype=np.float64)

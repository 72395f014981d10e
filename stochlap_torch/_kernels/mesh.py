"""``Lhat`` and ``alpha`` of a mesh in one numba pass, equal to the torch construction of
:mod:`stochlap_torch.operators`: a counting sort of the face corners by vertex, then a small
sort within each row."""

from __future__ import annotations

import numpy as np

from .._common.errors import ParameterError
from .jit import kernel_jit
from .threads import numba_available

if numba_available():
    # uint64 indices compile to plain loads (numba fixes up negative signed indices).
    _U = np.uint64

    @kernel_jit(nogil=True)
    def _neighbours(faces, num_vertices):
        """``(start, neighbours)``: each vertex's distinct neighbours, ascending, in CSR form
        (int32 neighbours: the caller has ``V < 2**31``)."""
        # The two other corners of each face of each vertex (an interior edge is listed twice,
        # a non-manifold edge more), grouped by vertex.
        start = np.zeros(num_vertices + 1, dtype=np.int64)
        for f in range(faces.shape[0]):
            for k in range(3):
                start[faces[f, k] + 1] += 2
        for i in range(num_vertices):
            start[i + 1] += start[i]
        listed = np.empty(start[num_vertices], dtype=np.int32)  # V < 2**31 (the caller)
        cursor = start[:-1].copy()
        for f in range(faces.shape[0]):
            a, b, c = faces[f, 0], faces[f, 1], faces[f, 2]
            listed[_U(cursor[a])], listed[_U(cursor[a] + 1)] = b, c
            listed[_U(cursor[b])], listed[_U(cursor[b] + 1)] = c, a
            listed[_U(cursor[c])], listed[_U(cursor[c] + 1)] = a, b
            cursor[a] += 2
            cursor[b] += 2
            cursor[c] += 2
        # The few distinct neighbours of a vertex are placed by counting the smaller ones (no
        # data-dependent branch).
        mark = np.full(num_vertices, -1, dtype=np.int32)
        widest = 0
        for i in range(num_vertices):
            widest = max(widest, start[i + 1] - start[i])
        distinct = np.empty(widest, dtype=np.int32)
        kept = np.zeros(num_vertices + 1, dtype=np.int64)
        for i in range(num_vertices):
            count = 0
            for s in range(start[i], start[i + 1]):
                j = listed[_U(s)]
                distinct[_U(count)] = j
                count += mark[_U(j)] != i
                mark[_U(j)] = i
            for p in range(count):
                value, rank = distinct[_U(p)], 0
                for q in range(count):
                    rank += distinct[_U(q)] < value
                listed[_U(start[i] + rank)] = value
            kept[i + 1] = kept[i] + count
        neighbours = np.empty(kept[num_vertices], dtype=np.int32)
        for i in range(num_vertices):
            neighbours[kept[i] : kept[i + 1]] = listed[start[i] : start[i] + kept[i + 1] - kept[i]]
        return kept, neighbours

    # error_model='numpy': a zero-length edge gives an infinite weight (reported through
    # ``finite``), not a ZeroDivisionError.
    @kernel_jit(nogil=True, error_model="numpy")
    def _assemble(vertices, start, neighbours, one):
        """``(crow, col, val, alpha, finite)`` from the neighbour lists. Weights and lengths
        are computed in the vertices' dtype, as in the torch construction; ``alpha`` in
        float64 (its mean edge length sums every edge), rounded to that dtype."""
        num_vertices = vertices.shape[0]
        num_edges = neighbours.shape[0] // 2
        crow = np.empty(num_vertices + 1, dtype=np.int64)
        col = np.empty(neighbours.shape[0] + num_vertices, dtype=np.int64)
        val = np.empty(neighbours.shape[0] + num_vertices, dtype=vertices.dtype)
        length_sum = np.zeros(num_vertices, dtype=vertices.dtype)
        all_lengths = 0.0
        finite = True
        crow[0] = 0
        for i in range(num_vertices):
            slot = crow[i]
            degree = one - one  # zero in the vertices' dtype
            diagonal_slot = -1
            for s in range(start[i], start[i + 1]):
                j = neighbours[s]
                if j > i and diagonal_slot < 0:
                    diagonal_slot = slot
                    slot += 1
                dx = vertices[i, 0] - vertices[j, 0]
                dy = vertices[i, 1] - vertices[j, 1]
                dz = vertices[i, 2] - vertices[j, 2]
                squared = dx * dx + dy * dy + dz * dz
                weight = one / squared
                finite &= np.isfinite(weight)
                col[slot], val[slot] = j, weight
                slot += 1
                degree += weight
                length = np.sqrt(squared)
                length_sum[i] += length
                if j > i:
                    all_lengths += length
            if diagonal_slot < 0:
                diagonal_slot = slot
                slot += 1
            col[diagonal_slot] = i
            val[diagonal_slot] = degree if degree > 0 else one
            crow[i + 1] = slot
        # alpha(i) = c n_i / sum_j |Pi - Pj| + 1, c the mean edge length; 1 without edges.
        mean_length = all_lengths / max(num_edges, 1)
        alpha = np.empty(num_vertices, dtype=vertices.dtype)
        for i in range(num_vertices):
            count = start[i + 1] - start[i]
            alpha[i] = mean_length * count / length_sum[i] + 1.0 if count > 0 else one
        return crow, col, val, alpha, finite


def lhat_parts(vertices: np.ndarray, faces: np.ndarray) -> tuple:
    """``Lhat`` and ``alpha`` of a validated mesh (its edges are ``Lhat``'s entries above the
    diagonal: :attr:`stochlap_torch.operators.MeshOperators.edges`).

    Args:
        vertices: ``(V, 3)`` float32 or float64, C-contiguous.
        faces: ``(F, 3)`` int64, indices in range, no repeated vertex within a face.

    Returns:
        ``(crow, col, val, alpha, finite)``: ``Lhat`` in CSR form (columns ascending within
        each row) and ``(V,)`` ``alpha`` (Eq. 9) in the dtype of the vertices, and whether
        every edge has a non-zero length (the caller raises, naming the others).

    Raises:
        ParameterError: ``V >= 2**31`` (the kernel lists neighbours with 4-byte indices).
    """
    if vertices.shape[0] >= 2**31:
        raise ParameterError("lhat_parts handles fewer than 2**31 vertices")
    start, neighbours = _neighbours(faces, vertices.shape[0])
    return _assemble(vertices, start, neighbours, vertices.dtype.type(1))

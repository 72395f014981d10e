"""Reductions of point values over Euclidean balls, for Lee et al.'s Gaussian filters.

By default a numba kernel scans the 27 cells around each point of a uniform grid of cubes as
wide as the largest radius and accumulates as it goes, on the thread driver of
:mod:`stochlap_torch._kernels`: a k-d tree would first list every pair within that radius,
which grows with the square of the radius. Without numba, a ``scipy.spatial.cKDTree`` lists
the pairs in chunks of points.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from .._common.errors import ParameterError
from .._kernels import kernel_jit, kernel_thread_count, numba_available, run_workers

__all__ = ["ball_reduce"]

#: Points per part a kernel worker takes.
_CHUNK = 256
#: Roughly how many neighbour pairs one chunk of the k-d tree query may list.
_PAIRS_PER_CHUNK = 4_000_000

if numba_available():
    from .._kernels.threads import next_part

    @kernel_jit(nogil=True)
    def _ball_worker(
        thread, counter, points, values, radii, gaussian, cells, dims, keys, starts, out, den
    ):  # pragma: no cover - compiled
        """:func:`ball_reduce` on points sorted by cell, for the parts taken from ``counter``:
        the points of the 27 cells around each point's cell, accumulated as they are found."""
        while True:
            first = next_part(counter) * _CHUNK
            if first >= points.shape[0]:
                break
            for i in range(first, min(first + _CHUNK, points.shape[0])):
                for cell in range(27):
                    x = cells[i, 0] + cell // 9 - 1
                    y = cells[i, 1] + cell // 3 % 3 - 1
                    z = cells[i, 2] + cell % 3 - 1
                    if not (0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]):
                        continue
                    key = (x * dims[1] + y) * dims[2] + z
                    slot = np.searchsorted(keys, key)
                    if slot == keys.shape[0] or keys[slot] != key:
                        continue
                    for j in range(starts[slot], starts[slot + 1]):
                        d2 = 0.0
                        for a in range(3):
                            diff = points[i, a] - points[j, a]
                            d2 += diff * diff
                        for s in range(radii.shape[0]):
                            if d2 > radii[s] * radii[s]:
                                break
                            if gaussian:
                                w = math.exp(-d2 / (0.5 * radii[s] * radii[s]))
                                out[s, i] += w * values[0, j]
                                den[s, i] += w
                            elif values[s, j] > out[s, i]:
                                out[s, i] = values[s, j]


def _grid(points: np.ndarray, cell: float):
    """``(order, cells, dims, keys, starts)`` of a grid of cubes of side ``cell`` over
    ``(N, 3)`` points: the point indices in cell order, the ``(N, 3)`` int64 cells of the
    sorted points, the ``(3,)`` grid size, the sorted keys ``(x dims[1] + y) dims[2] + z`` of
    the ``C`` occupied cells and the ``(C + 1,)`` offsets of their points."""
    cells = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) > 2.0**62:
        raise ParameterError(f"epsilon {cell:g} is too small for a grid over this mesh")
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(key, kind="stable")
    keys, counts = np.unique(key[order], return_counts=True)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return order, np.ascontiguousarray(cells[order]), dims, keys, starts


def _pair_chunks(points: np.ndarray, radius: float):
    """Yield ``(rows, cols, dist)`` for all pairs within ``radius``, chunked over rows."""
    from scipy import spatial

    tree = spatial.cKDTree(points)
    sample = points[:: max(1, points.shape[0] // 256)]
    per_point = max(1.0, float(np.mean(tree.query_ball_point(sample, radius, return_length=True))))
    chunk = max(64, int(_PAIRS_PER_CHUNK / per_point))
    for start in range(0, points.shape[0], chunk):
        block = spatial.cKDTree(points[start : start + chunk])
        pairs = block.sparse_distance_matrix(tree, radius, output_type="ndarray")
        yield pairs["i"] + start, pairs["j"], pairs["v"]


def ball_reduce(points, values, radii, gaussian: bool, use_numba: bool) -> np.ndarray:
    """``values`` reduced over the ball of each radius around each point.

    Args:
        points: ``(N, 3)`` float64.
        values: ``(1, N)`` float64 with ``gaussian``, else ``(S, N)``.
        radii: ``(S,)`` float64, descending.
        gaussian: average ``values[0]`` with weights ``w = exp(-d^2 / 2 sigma^2)``,
            ``sigma = radii[s] / 2``, instead of taking the largest ``values[s]``.
        use_numba: the grid kernel, else the k-d tree.

    Returns:
        ``(S, N)`` float64: ``sum w values / sum w``, or the largest value within ``radii[s]``.
    """
    out = np.zeros((len(radii), len(points))) if gaussian else np.full_like(values, -np.inf)
    den = np.zeros_like(out)
    if use_numba:
        order, *arrays = _grid(points, float(radii[0]))
        threads = kernel_thread_count(torch.get_num_threads(), -(-len(points) // _CHUNK))
        sorted_points = np.ascontiguousarray(points[order])
        sorted_values = np.ascontiguousarray(values[:, order])
        args = (sorted_points, sorted_values, radii, gaussian, *arrays, out, den)
        run_workers(_ball_worker, threads, np.zeros(1, dtype=np.int64), *args)
        result = np.empty_like(out)
        result[:, order] = out / den if gaussian else out
        return result
    for rows, cols, dist in _pair_chunks(points, float(radii[0])):
        for s, radius in enumerate(radii):
            inside = dist <= radius
            r, c, d = rows[inside], cols[inside], dist[inside]
            if gaussian:
                w = np.exp(-(d * d) / (0.5 * radius * radius))
                out[s] += np.bincount(r, weights=w * values[0, c], minlength=len(points))
                den[s] += np.bincount(r, weights=w, minlength=len(points))
            else:
                np.maximum.at(out[s], r, values[s, c])
    return out / den if gaussian else out

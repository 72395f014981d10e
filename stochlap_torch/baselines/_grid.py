"""Point neighbourhoods on a uniform grid of cubes, for Lee et al.'s Gaussian filters.

Hand-written because scipy's k-d tree would list every pair within the largest filter radius
(tens of millions at 50k vertices); these kernels visit the 27 cells around each point and
accumulate as they go. They run on the thread driver of :mod:`stochlap_torch._kernels`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from .._common.errors import ParameterError
from .._kernels import kernel_jit, kernel_thread_count, numba_available, run_workers

if numba_available():
    from numba import njit

    from .._kernels.threads import next_part

__all__ = ["Grid", "gaussian_worker", "grid", "max_worker", "run_grid_kernel"]


if numba_available():

    @njit(nogil=True, inline="always")
    def _cell_range(keys, starts, key):  # pragma: no cover - compiled
        """``[start, stop)`` of the points of cell ``key`` in grid order (empty if none)."""
        slot = np.searchsorted(keys, key)
        if slot < keys.shape[0] and keys[slot] == key:
            return starts[slot], starts[slot + 1]
        return 0, 0

    @njit(nogil=True)
    def _neighbours_within(i, reach, points, cells, dims, keys, starts, found_j, found_d2):
        """The points within ``reach`` of point ``i`` (itself included), from the 27 cells
        around its cell: their indices into ``found_j`` and squared distances into
        ``found_d2`` (grown as needed); return ``(count, found_j, found_d2)``."""
        count = 0
        limit = reach * reach
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    x, y, z = cells[i, 0] + dx, cells[i, 1] + dy, cells[i, 2] + dz
                    if not (0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]):
                        continue
                    start, stop = _cell_range(keys, starts, (x * dims[1] + y) * dims[2] + z)
                    for j in range(start, stop):
                        d2 = 0.0
                        for a in range(3):
                            diff = points[i, a] - points[j, a]
                            d2 += diff * diff
                        if d2 > limit:
                            continue
                        if count == found_j.shape[0]:
                            found_j = np.concatenate((found_j, np.empty_like(found_j)))
                            found_d2 = np.concatenate((found_d2, np.empty_like(found_d2)))
                        found_j[count], found_d2[count] = j, d2
                        count += 1
        return count, found_j, found_d2

    @kernel_jit(nogil=True)
    def gaussian_worker(
        thread, counter, chunk, points, values, sigmas, cells, dims, keys, starts, num, den
    ):  # pragma: no cover - compiled
        """For every point ``i`` (chunks of ``chunk`` points taken from ``counter``) and
        ``sigmas[s]`` (descending), the sums over the points ``j`` within ``2 sigmas[s]`` of
        ``w values[j]`` and ``w = exp(-d^2 / 2 sigma^2)``. The points are sorted by cell (see
        :func:`grid`)."""
        found_j, found_d2 = np.empty(256, dtype=np.int64), np.empty(256)
        while True:
            first = next_part(counter) * chunk
            if first >= points.shape[0]:
                break
            for i in range(first, min(first + chunk, points.shape[0])):
                count, found_j, found_d2 = _neighbours_within(
                    i, 2.0 * sigmas[0], points, cells, dims, keys, starts, found_j, found_d2
                )
                for t in range(count):
                    j, d2 = found_j[t], found_d2[t]
                    for s in range(sigmas.shape[0]):
                        if d2 > 4.0 * sigmas[s] * sigmas[s]:
                            break
                        w = math.exp(-d2 / (2.0 * sigmas[s] * sigmas[s]))
                        num[s, i] += w * values[j]
                        den[s, i] += w

    @kernel_jit(nogil=True)
    def max_worker(
        thread, counter, chunk, points, maps, radii, cells, dims, keys, starts, out
    ):  # pragma: no cover - compiled
        """``out[s, i] = max maps[s, j]`` over the points ``j`` within ``radii[s]``
        (descending) of ``i``, for the chunks of points taken from ``counter``."""
        found_j, found_d2 = np.empty(256, dtype=np.int64), np.empty(256)
        while True:
            first = next_part(counter) * chunk
            if first >= points.shape[0]:
                break
            for i in range(first, min(first + chunk, points.shape[0])):
                count, found_j, found_d2 = _neighbours_within(
                    i, radii[0], points, cells, dims, keys, starts, found_j, found_d2
                )
                for t in range(count):
                    j, d2 = found_j[t], found_d2[t]
                    for s in range(radii.shape[0]):
                        if d2 > radii[s] * radii[s]:
                            break
                        if maps[s, j] > out[s, i]:
                            out[s, i] = maps[s, j]


def run_grid_kernel(worker, points: np.ndarray, *args) -> None:
    """Run a grid worker over all points on the caller's torch thread count (no native
    thread pool: see :mod:`stochlap_torch._kernels.threads`)."""
    chunk = 256
    parts = -(-points.shape[0] // chunk)
    threads = kernel_thread_count(torch.get_num_threads(), parts)
    run_workers(worker, threads, np.zeros(1, dtype=np.int64), chunk, points, *args)


@dataclass(frozen=True)
class Grid:
    """A uniform grid of cubes over points, with the points sorted by cell.

    Attributes:
        order: ``(N,)`` the point indices in cell order (``sorted = points[order]``).
        cells: ``(N, 3)`` int64 cell coordinates of the sorted points.
        dims: ``(3,)`` int64 grid size.
        keys: ``(C,)`` sorted keys ``(x dims[1] + y) dims[2] + z`` of the occupied cells.
        starts: ``(C + 1,)`` offsets of each occupied cell's points in the sorted order.
    """

    order: np.ndarray
    cells: np.ndarray
    dims: np.ndarray
    keys: np.ndarray
    starts: np.ndarray

    def arrays(self) -> tuple[np.ndarray, ...]:
        return self.cells, self.dims, self.keys, self.starts


def grid(points: np.ndarray, cell: float) -> Grid:
    """The :class:`Grid` of cubes of side ``cell`` over ``(N, 3)`` points."""
    low = points.min(axis=0)
    cells = np.floor((points - low) / cell).astype(np.int64)
    dims = cells.max(axis=0) + 1
    if float(np.prod(dims.astype(np.float64))) > 2.0**62:
        raise ParameterError(f"epsilon {cell:g} is too small for a grid over this mesh")
    key = (cells[:, 0] * dims[1] + cells[:, 1]) * dims[2] + cells[:, 2]
    order = np.argsort(key, kind="stable")
    keys, counts = np.unique(key[order], return_counts=True)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    return Grid(order, np.ascontiguousarray(cells[order]), dims, keys, starts)

"""Row ranges of a step: whole blocks of rows, balanced by work, and their output regions."""

from __future__ import annotations

import math

import numpy as np

from ._numba import numba_available
from .block import LANES
from .jit import kernel_jit

__all__ = ["block_parts", "regions"]


if numba_available():

    @kernel_jit(nogil=True)
    def regions(part_first, part_last, counts, products, num_cols, factor, used):
        """Back-to-back ``[start, end)`` output regions of the parts, from ``used`` on.

        Row ``i`` gets room for ``ceil(factor * counts[i]) + 2`` entries, at most its bound
        ``min(products[i], V)``; with ``factor < 0``, the bound itself (a round that cannot
        overflow).
        """
        start = np.empty(part_first.shape[0], dtype=np.int64)
        end = np.empty(part_first.shape[0], dtype=np.int64)
        cursor = used
        for part in range(part_first.shape[0]):
            start[part] = cursor
            for i in range(part_first[part], part_last[part]):
                room = min(products[i], num_cols)
                if factor >= 0:
                    room = min(room, math.ceil(factor * counts[i]) + 2)
                cursor += room
            end[part] = cursor
        return start, end

    @kernel_jit(nogil=True)
    def _balanced_parts(work, parts):
        """Split rows ``[0, n)`` into at most ``parts`` ranges ``[first, last)`` of about
        equal ``work``: a range ends before the row whose running total first exceeds the
        next ``p / parts`` of the total."""
        num_rows = work.shape[0]
        total = 0
        for i in range(num_rows):
            total += work[i]
        first = np.empty(max(parts, 1), dtype=np.int64)
        last = np.empty(max(parts, 1), dtype=np.int64)
        count, start, running, p = 0, 0, 0, 1
        for i in range(num_rows):
            running += work[i]
            while p < parts and running > total * p / parts:
                if start < i:  # a boundary before row i (empty ranges are skipped)
                    first[count], last[count] = start, i
                    count += 1
                    start = i
                p += 1
        if start < num_rows:
            first[count], last[count] = start, num_rows
            count += 1
        return first[:count], last[:count]


def block_parts(
    block_work: np.ndarray, start: int, stop: int, parts: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``[start, stop)`` (``start`` a multiple of :data:`LANES`) in at most ``parts``
    ranges ``[first, last)`` of whole blocks and about equal work (``block_work``, one value
    per block of the range), so that a row's block never depends on the split."""
    first, last = _balanced_parts(block_work, parts)
    return start + first * LANES, np.minimum(start + last * LANES, stop)

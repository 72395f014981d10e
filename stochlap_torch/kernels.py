"""Fused CPU kernel for one diffusion step, compiled with numba.

Row ``i`` of ``F^(k)`` depends only on row ``i`` of ``F^(k-1)``, ``Lhat`` and ``alpha``, so each
step is computed row by row in one pass, in parallel over contiguous row ranges, with a dense
accumulator per thread (Gustavson's algorithm)::

    row of F^(k-1) @ Lhat  ->  normalise  ->  threshold  ->  * alpha  ->  normalise

and, in the same pass, the difference map ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)`` and the
row ``P^(k)(i) = F^(k)(i, :) P``. Rows are processed in chunks whose padded output is bounded
(:data:`CHUNK_PRODUCTS`), so peak memory stays close to the size of ``F^(k-1)`` and ``F^(k)``.

Compiled functions are cached on disk (``cache=True``): only the first call on a machine pays
the compile time.
"""

from __future__ import annotations

import logging

import numpy as np

try:
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - numba is a dependency; kept for exotic platforms
    numba = None

__all__ = ["CHUNK_PRODUCTS", "SERIAL_ENTRIES", "available", "fused_step"]

logger = logging.getLogger(__name__)

#: Padded output entries one chunk of rows may reserve (bounds the transient memory).
CHUNK_PRODUCTS = 1 << 24
#: Row ranges per thread and chunk, handed out dynamically.
PARTS_PER_THREAD = 32
#: Below this many entries of ``F^(k-1)`` a step runs on one thread.
SERIAL_ENTRIES = 1 << 18


def available() -> bool:
    """Whether the compiled kernel can run here (numba importable)."""
    return numba is not None


if numba is not None:

    @njit(cache=True, nogil=True)
    def _row(
        i, f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points, sort_columns,
        acc, mark, previous, touched, out_col, out_val, base, new_points,
    ):  # fmt: skip
        """Compute row ``i`` into ``out_*[base:]``; return (count, difference).

        ``acc`` and ``previous`` are dense ``(V,)`` scratch rows (``previous`` all zero on entry
        and on exit), ``mark`` a ``(V,)`` stamp of the row that last touched a column.
        """
        count = 0
        for e in range(f_crow[i], f_crow[i + 1]):
            j = f_col[e]
            weight = f_val[e]
            for slot in range(l_crow[j], l_crow[j + 1]):
                c = l_col[slot]
                if mark[c] != i:
                    mark[c] = i
                    acc[c] = 0.0
                    touched[count] = c
                    count += 1
                acc[c] += weight * l_val[slot]
        total = 0.0
        largest = 0.0
        for t in range(count):
            value = acc[touched[t]]
            total += value
            largest = max(largest, value)
        # Normalise, threshold (the row maximum always survives), multiply by alpha.
        kept = 0
        scaled_total = 0.0
        for t in range(count):
            c = touched[t]
            value = acc[c] / total
            if value >= threshold or acc[c] == largest:
                out_col[base + kept] = c
                acc[c] = value * alpha[c]
                scaled_total += acc[c]
                kept += 1
        if sort_columns:  # canonical CSR; the steps themselves do not need it
            out_col[base : base + kept].sort()
        # Normalise again; accumulate P^(k)(i) and sum_j |F^(k)(i, j) - F^(k-1)(i, j)|, the
        # latter as sum |new - old| over the new row plus sum |old| off it.
        difference = 0.0
        for e in range(f_crow[i], f_crow[i + 1]):
            previous[f_col[e]] = f_val[e]
            difference += abs(f_val[e])
        for d in range(points.shape[1]):
            new_points[i, d] = 0.0
        for t in range(kept):
            c = out_col[base + t]
            value = acc[c] / scaled_total
            out_val[base + t] = value
            for d in range(points.shape[1]):
                new_points[i, d] += value * points[c, d]
            difference += abs(value - previous[c]) - abs(previous[c])
        for e in range(f_crow[i], f_crow[i + 1]):
            previous[f_col[e]] = 0.0
        return kept, difference

    @njit(cache=True, parallel=True, nogil=True)
    def _chunk(
        start, stop, bounds, f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold,
        points, sort_columns, padded_start, counts, differences, new_points, out_col, out_val,
        acc, mark, previous,
    ):  # fmt: skip
        """Rows ``[start, stop)``, split into ``len(bounds) - 1`` ranges run in parallel.

        ``acc`` and ``mark`` are ``(threads, V)`` scratch rows, one per thread.
        """
        for part in prange(bounds.shape[0] - 1):
            thread = numba.get_thread_id()
            thread_acc = acc[thread]  # views taken once per part, not once per row
            thread_mark = mark[thread]
            thread_previous = previous[thread]
            widest = 0
            for i in range(bounds[part], bounds[part + 1]):
                widest = max(widest, padded_start[i - start + 1] - padded_start[i - start])
            touched = np.empty(widest, dtype=np.int64)
            for i in range(bounds[part], bounds[part + 1]):
                kept, difference = _row(
                    i, f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points,
                    sort_columns, thread_acc, thread_mark, thread_previous, touched, out_col,
                    out_val,
                    padded_start[i - start], new_points,
                )  # fmt: skip
                counts[i] = kept
                differences[i] = difference

    @njit(cache=True, parallel=True, nogil=True)
    def _compact(start, stop, padded_start, crow, in_col, in_val, col, val):
        """Copy padded rows ``[start, stop)`` to their final places ``crow[i]`` in col/val."""
        for i in prange(start, stop):
            source = padded_start[i - start]
            target = crow[i]
            for t in range(crow[i + 1] - crow[i]):
                col[target + t] = in_col[source + t]
                val[target + t] = in_val[source + t]

    @njit(cache=True, parallel=True, nogil=True)
    def _products(f_crow, f_col, l_crow):
        """``(n,)`` scalar products each row of ``F @ Lhat`` costs."""
        products = np.zeros(f_crow.shape[0] - 1, dtype=np.int64)
        for i in prange(f_crow.shape[0] - 1):
            total = 0
            for e in range(f_crow[i], f_crow[i + 1]):
                total += l_crow[f_col[e] + 1] - l_crow[f_col[e]]
            products[i] = total
        return products


def _chunks(widths: np.ndarray, budget: int) -> list[tuple[int, int]]:
    """Contiguous ``[start, stop)`` row ranges of at most ``budget`` padded entries each."""
    cumulative = np.cumsum(widths)
    chunks, start = [], 0
    while start < widths.shape[0]:
        done = cumulative[start - 1] if start else 0
        stop = int(np.searchsorted(cumulative, done + budget, side="right"))
        chunks.append((start, max(stop, start + 1)))
        start = chunks[-1][1]
    return chunks


def _grow(array: np.ndarray, used: int, needed: int) -> np.ndarray:
    """``array`` if it holds ``needed`` entries, else a larger copy of its first ``used``."""
    if needed <= array.shape[0]:
        return array
    larger = np.empty(max(needed, 2 * array.shape[0]), dtype=array.dtype)
    larger[:used] = array[:used]
    return larger


def _thread_bounds(work: np.ndarray, start: int, stop: int, parts: int) -> np.ndarray:
    """Split rows ``[start, stop)`` into ``parts`` ranges of about equal ``work``."""
    cumulative = np.cumsum(work[start:stop])
    if cumulative.size == 0:
        return np.array([start, stop], dtype=np.int64)
    targets = cumulative[-1] * np.arange(1, parts) / parts
    inner = start + np.searchsorted(cumulative, targets, side="right")
    return np.unique(np.concatenate([[start], inner, [stop]])).astype(np.int64)


def fused_step(
    f_crow: np.ndarray, f_col: np.ndarray, f_val: np.ndarray,
    l_crow: np.ndarray, l_col: np.ndarray, l_val: np.ndarray,
    alpha: np.ndarray, threshold: float, points: np.ndarray, num_threads: int,
    sort_columns: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """One diffusion step on CPU arrays.

    Args:
        f_crow, f_col, f_val: ``F^(k-1)`` in CSR form, ``(V + 1,)``, ``(nnz,)``, ``(nnz,)``.
        l_crow, l_col, l_val: ``Lhat`` in CSR form.
        alpha: ``(V,)`` scale invariance function.
        threshold: ``lambda``.
        points: ``(V, C)`` positions ``P`` (any number of channels).
        num_threads: threads to use.
        sort_columns: sort the columns within each row (canonical CSR). The steps do not need
            it, so the diffusion loop skips it unless the operators are returned.

    Returns:
        ``(crow, col, val)`` of ``F^(k)``, the ``(V,)`` difference map and ``(V, C)``
        ``F^(k) P``.
    """
    if numba is None:
        raise RuntimeError("the fused kernel needs numba: pip install numba")
    # Small steps run on one thread: waking the pool costs more than it saves.
    wanted = 1 if f_col.shape[0] < SERIAL_ENTRIES else num_threads
    numba.set_num_threads(max(1, min(wanted, numba.config.NUMBA_NUM_THREADS)))
    threads = numba.get_num_threads()
    # Hand out row ranges one at a time: a thread that the OS parks (shared cores) then holds
    # up one small range, not a fixed half of the rows.
    previous_chunksize = numba.set_parallel_chunksize(1)
    try:
        num_rows = f_crow.shape[0] - 1
        num_cols = l_crow.shape[0] - 1
        # A row of F^(k-1) @ Lhat has at most min(products, V) columns: its padded width.
        products = _products(f_crow, f_col, l_crow)
        widths = np.minimum(products, num_cols)
        chunks = _chunks(widths, CHUNK_PRODUCTS)
        padded_size = max(int(widths[a:b].sum()) for a, b in chunks)
        # Reused by every chunk: fresh memory is slow to touch on virtual machines.
        padded_col = np.empty(padded_size, dtype=np.int64)
        padded_val = np.empty(padded_size, dtype=f_val.dtype)

        crow = np.zeros(num_rows + 1, dtype=np.int64)
        differences = np.zeros(num_rows, dtype=f_val.dtype)
        new_points = np.zeros((num_rows, points.shape[1]), dtype=f_val.dtype)
        acc = np.zeros((threads, num_cols), dtype=f_val.dtype)
        mark = np.full((threads, num_cols), -1, dtype=np.int64)
        previous = np.zeros((threads, num_cols), dtype=f_val.dtype)
        capacity = min(int(widths.sum()), 3 * f_col.shape[0] + num_rows)
        col = np.empty(capacity, dtype=np.int64)
        val = np.empty(capacity, dtype=f_val.dtype)
        counts = crow[1:]  # the kernel writes row counts here; turned into offsets per chunk
        for start, stop in chunks:
            padded_start = np.zeros(stop - start + 1, dtype=np.int64)
            np.cumsum(widths[start:stop], out=padded_start[1:])
            bounds = _thread_bounds(products, start, stop, PARTS_PER_THREAD * threads)
            _chunk(start, stop, bounds, f_crow, f_col, f_val, l_crow, l_col, l_val, alpha,
                   threshold, points, sort_columns, padded_start, counts, differences, new_points,
                   padded_col, padded_val, acc, mark, previous)  # fmt: skip
            np.cumsum(crow[start : stop + 1], out=crow[start : stop + 1])
            col = _grow(col, crow[start], crow[stop])
            val = _grow(val, crow[start], crow[stop])
            _compact(start, stop, padded_start, crow, padded_col, padded_val, col, val)
    finally:
        numba.set_parallel_chunksize(previous_chunksize)
    return crow, col[: crow[-1]], val[: crow[-1]], differences, new_points

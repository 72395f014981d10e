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

__all__ = ["CHUNK_PRODUCTS", "SERIAL_ENTRIES", "Workspace", "available", "fused_step"]

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

        ``acc`` and ``mark`` are ``(threads, V)`` scratch rows, one per thread. The rows of a
        range are written one after the other from the range's padded start, so that
        :func:`_compact` moves each range with one contiguous copy.
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
            cursor = padded_start[bounds[part] - start]
            for i in range(bounds[part], bounds[part + 1]):
                kept, difference = _row(
                    i, f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points,
                    sort_columns, thread_acc, thread_mark, thread_previous, touched, out_col,
                    out_val, cursor, new_points,
                )  # fmt: skip
                cursor += kept
                counts[i] = kept
                differences[i] = difference

    @njit(cache=True, parallel=True, nogil=True)
    def _compact(start, bounds, padded_start, crow, in_col, in_val, col, val):
        """Copy each row range of :func:`_chunk` to its final place ``crow[first row]``."""
        for part in prange(bounds.shape[0] - 1):
            first, last = bounds[part], bounds[part + 1]
            source = padded_start[first - start]
            size = crow[last] - crow[first]
            col[crow[first] : crow[first] + size] = in_col[source : source + size]
            val[crow[first] : crow[first] + size] = in_val[source : source + size]

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


def _run_dynamic(function, *args):
    """Call a parallel kernel with its ``prange`` iterations handed out one at a time.

    A thread that the OS parks (cores shared with other work) then holds up one small row
    range, not a fixed share of the rows.
    """
    previous = numba.set_parallel_chunksize(1)
    try:
        return function(*args)
    finally:
        numba.set_parallel_chunksize(previous)


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


class Workspace:
    """Buffers that consecutive steps of one run reuse instead of allocating afresh.

    On virtual machines that hand freed memory back to the host, touching freshly allocated
    pages costs about as much as the arithmetic of a step (0.6 s for 400 MB, measured here),
    so a run keeps its scratch rows, its padded chunk buffer and two output buffers that the
    steps use in turn. The ``F^(k)`` a step returns is a view into one output buffer, valid
    until the step after next: hold at most the current and the previous operator.

    Args:
        num_rows, num_cols: shape of ``F``.
        dtype: value dtype.
        capacity: expected stored entries of the largest ``F^(k)`` (grown when exceeded).
    """

    def __init__(self, num_rows: int, num_cols: int, dtype, capacity: int):
        self.num_rows, self.num_cols, self.dtype = num_rows, num_cols, np.dtype(dtype)
        self.outputs = [
            (np.empty(capacity, dtype=np.int64), np.empty(capacity, dtype=self.dtype))
            for _ in range(2)
        ]
        self.turn = 0
        self.padded = (np.empty(0, dtype=np.int64), np.empty(0, dtype=self.dtype))
        self.scratch_threads = 0

    def padded_buffers(self, size: int) -> tuple[np.ndarray, np.ndarray]:
        """``(size,)`` int64 and value buffers for one chunk of padded rows."""
        if self.padded[0].shape[0] < size:
            self.padded = (np.empty(size, dtype=np.int64), np.empty(size, dtype=self.dtype))
        return self.padded

    def scratch(self, threads: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per-thread dense rows ``acc``, ``mark`` (reset to -1) and ``previous`` (zero)."""
        if self.scratch_threads < threads:
            shape = (threads, self.num_cols)
            self.acc = np.zeros(shape, dtype=self.dtype)
            self.mark = np.empty(shape, dtype=np.int64)
            self.previous = np.zeros(shape, dtype=self.dtype)
            self.scratch_threads = threads
        self.mark.fill(-1)  # stamps are row indices: clear the last step's
        return self.acc, self.mark, self.previous

    def next_output(self) -> tuple[np.ndarray, np.ndarray]:
        """The output buffer pair whose contents are two steps old."""
        self.turn ^= 1
        return self.outputs[self.turn]

    def keep_output(self, col: np.ndarray, val: np.ndarray) -> None:
        """Remember a buffer pair that a step had to grow."""
        self.outputs[self.turn] = (col, val)


def fused_step(
    f_crow: np.ndarray, f_col: np.ndarray, f_val: np.ndarray,
    l_crow: np.ndarray, l_col: np.ndarray, l_val: np.ndarray,
    alpha: np.ndarray, threshold: float, points: np.ndarray, num_threads: int,
    sort_columns: bool = True, workspace: Workspace | None = None,
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
        workspace: reuse its buffers (the returned ``col``/``val`` are then views into it, see
            :class:`Workspace`); ``None`` allocates fresh arrays.

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
    num_rows = f_crow.shape[0] - 1
    num_cols = l_crow.shape[0] - 1
    if workspace is None:
        workspace = Workspace(num_rows, num_cols, f_val.dtype, 0)
    # A row of F^(k-1) @ Lhat has at most min(products, V) columns: its padded width.
    products = _products(f_crow, f_col, l_crow)
    widths = np.minimum(products, num_cols)
    chunks = _chunks(widths, CHUNK_PRODUCTS)
    padded_col, padded_val = workspace.padded_buffers(
        max(int(widths[a:b].sum()) for a, b in chunks)
    )
    acc, mark, previous = workspace.scratch(threads)
    col, val = workspace.next_output()
    if col.shape[0] == 0:  # no workspace: room for a typical step, grown when needed
        capacity = min(int(widths.sum()), 3 * f_col.shape[0] + num_rows)
        col, val = np.empty(capacity, dtype=np.int64), np.empty(capacity, dtype=f_val.dtype)

    crow = np.zeros(num_rows + 1, dtype=np.int64)
    differences = np.zeros(num_rows, dtype=f_val.dtype)
    new_points = np.zeros((num_rows, points.shape[1]), dtype=f_val.dtype)
    counts = crow[1:]  # the kernel writes row counts here; turned into offsets per chunk
    for start, stop in chunks:
        padded_start = np.zeros(stop - start + 1, dtype=np.int64)
        np.cumsum(widths[start:stop], out=padded_start[1:])
        bounds = _thread_bounds(products, start, stop, PARTS_PER_THREAD * threads)
        _run_dynamic(_chunk, start, stop, bounds, f_crow, f_col, f_val, l_crow, l_col, l_val,
                     alpha, threshold, points, sort_columns, padded_start, counts, differences,
                     new_points, padded_col, padded_val, acc, mark, previous)  # fmt: skip
        np.cumsum(crow[start : stop + 1], out=crow[start : stop + 1])
        col = _grow(col, crow[start], crow[stop])
        val = _grow(val, crow[start], crow[stop])
        _compact(start, bounds, padded_start, crow, padded_col, padded_val, col, val)
    workspace.keep_output(col, val)
    return crow, col[: crow[-1]], val[: crow[-1]], differences, new_points

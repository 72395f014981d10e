"""Fused CPU kernel for one diffusion step, compiled with numba.

Row ``i`` of ``F^(k)`` depends only on row ``i`` of ``F^(k-1)``, ``Lhat`` and ``alpha``, so each
step is computed row by row in one pass, in parallel over row ranges, with a dense accumulator
per thread (Gustavson's algorithm)::

    row of F^(k-1) @ Lhat  ->  normalise  ->  threshold  ->  * alpha  ->  normalise

and, in the same pass, the difference map ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)``, the
row ``P^(k)(i) = F^(k)(i, :) P`` and the cost of the row in the next step.

Each row range writes its rows back to back into a region of the output sized from an
estimate of the row lengths (``growth`` times the input row lengths). A row that does not fit
stops its range; the rest of the range is redone in a later round with larger regions, the
last round with regions that cannot overflow. The result is :class:`Rows`, a CSR whose rows
may be separated by gaps, so no step copies its output; :meth:`Rows.to_csr` packs it when a
canonical CSR is needed.

Compiled functions are cached on disk (``cache=True``): only the first call on a machine pays
the compile time.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

try:
    import numba
    from numba import njit, prange
except ImportError:  # pragma: no cover - numba is a dependency; kept for exotic platforms
    numba = None

__all__ = [
    "DEFAULT_GROWTH",
    "DEFAULT_POOL_BYTES",
    "SERIAL_ENTRIES",
    "WORKSPACES",
    "Rows",
    "SplitLhat",
    "Workspace",
    "WorkspacePool",
    "available",
    "first_rows",
    "fused_step",
    "growth_from_entries",
    "index_dtype",
    "prefaulted_zeros",
]

logger = logging.getLogger(__name__)

#: Row ranges per thread, handed out dynamically.
PARTS_PER_THREAD = 32
#: Below this many entries of ``F^(k-1)`` a step runs on one thread.
SERIAL_ENTRIES = 1 << 18
#: Output room per input entry when nothing better is known (a first step grows ~3x).
DEFAULT_GROWTH = 3.0
#: Rounds with estimated regions before the last, overflow-free one.
_ESTIMATED_ROUNDS = 3
#: Bytes of idle workspaces kept between runs (see :class:`WorkspacePool`).
DEFAULT_POOL_BYTES = 256 * 2**20


def available() -> bool:
    """Whether the compiled kernel can run here (numba importable)."""
    return numba is not None


if numba is not None:
    # Array indices of type uint64 compile to plain loads: numba adds a negative-index fix-up
    # to every signed index, which costs about a sixth of the hot loop below.
    _U = np.uint64

    @njit(cache=True, nogil=True)
    def _split_diagonal(l_crow, l_col, l_val):
        """``Lhat = diag(d) + W``: ``(d, w_crow, w_col, w_val, row_sums)``, ``W`` without the
        diagonal and ``row_sums`` those of ``Lhat``."""
        num_rows = l_crow.shape[0] - 1
        diagonal = np.zeros(num_rows, dtype=l_val.dtype)
        row_sums = np.zeros(num_rows, dtype=l_val.dtype)
        w_crow = np.zeros(num_rows + 1, dtype=np.int64)
        w_col = np.empty(l_col.shape[0], dtype=l_col.dtype)
        w_val = np.empty(l_col.shape[0], dtype=l_val.dtype)
        count = 0
        for i in range(num_rows):
            for slot in range(l_crow[i], l_crow[i + 1]):
                row_sums[i] += l_val[slot]
                if l_col[slot] == i:
                    diagonal[i] += l_val[slot]
                else:
                    w_col[count] = l_col[slot]
                    w_val[count] = l_val[slot]
                    count += 1
            w_crow[i + 1] = count
        return diagonal, w_crow, w_col[:count], w_val[:count], row_sums

    @njit(cache=True, nogil=True)
    def _normalised_rows(crow, col, val, row_sums, rows, out_col):
        """Rows ``rows`` of the CSR ``(crow, col, val)`` divided by ``row_sums``, packed:
        ``(out_crow, out_val)``, the columns written to ``out_col`` (in their index dtype)."""
        out_crow = np.zeros(rows.shape[0] + 1, dtype=np.int64)
        for r in range(rows.shape[0]):
            out_crow[r + 1] = out_crow[r] + crow[rows[r] + 1] - crow[rows[r]]
        out_val = np.empty(out_crow[-1], dtype=val.dtype)
        for r in range(rows.shape[0]):
            i = rows[r]
            offset = out_crow[r] - crow[i]
            for slot in range(crow[i], crow[i + 1]):
                out_col[slot + offset] = col[slot]
                out_val[slot + offset] = val[slot] / row_sums[i]
        return out_crow, out_val

    # Inlined into its callers: a call passes ~20 arrays, and numba counts a reference to
    # each one on the way in and out, which cost as much as the row's arithmetic.
    @njit(cache=True, nogil=True, inline="always")
    def _row(
        i, f_start, f_count, f_col, f_val, diagonal, w_crow, w_col, w_val, row_sums, alpha,
        threshold, points, sort_columns, acc, touched, out_col, out_val, base, new_points,
        target,
    ):  # fmt: skip
        """Compute row ``i`` into ``out_*[base:]`` and ``new_points[target]``; return
        (count, difference, next cost).

        ``acc`` is a dense ``(V,)`` scratch row, all zero on entry and on exit. Every product
        is positive, so a column is new to the row exactly when its ``acc`` is still zero:
        the test needs no branch and no second array (a product that underflows to zero
        leaves its column out, as it contributes nothing). ``touched`` needs room for the
        row's number of products plus one. The row sum of ``F^(k-1)(i, :) Lhat`` is taken
        from ``row_sums`` (those of ``Lhat``), so the product loop carries no running sum.
        """
        first, last = f_start[i], f_start[i] + f_count[i]
        # F^(k-1)(i, :) Lhat: the diagonal first (its columns are the row's own), then W.
        count = 0
        total = 0.0
        for e in range(first, last):
            j = _U(f_col[_U(e)])
            weight = f_val[_U(e)]
            product = weight * diagonal[j]
            acc[j] = product
            total += weight * row_sums[j]
            touched[_U(count)] = j
            count += product > 0.0
        for e in range(first, last):
            j = _U(f_col[_U(e)])
            weight = f_val[_U(e)]
            for slot in range(_U(w_crow[j]), _U(w_crow[j + _U(1)])):
                c = _U(w_col[slot])
                product = weight * w_val[slot]
                touched[_U(count)] = c
                count += (acc[c] == 0.0) & (product > 0.0)
                acc[c] += product
        # The row maximum always survives the threshold. It can only fall below it when the
        # row holds more than 1 / threshold entries, so it is looked up only then.
        largest = np.inf
        if count * threshold > 0.5:
            largest = 0.0
            for t in range(count):
                largest = max(largest, acc[_U(touched[_U(t)])])
        # Normalise, threshold, multiply by alpha; dropped columns are zeroed on the way.
        kept = 0
        scaled_total = 0.0
        inverse = 1.0 / total
        for t in range(count):
            c = _U(touched[_U(t)])
            raw = acc[c]
            value = raw * inverse
            keep = (value >= threshold) | (raw == largest)
            out_col[_U(base + kept)] = c
            kept += keep
            scaled = value * alpha[c] if keep else 0.0
            acc[c] = scaled
            scaled_total += scaled
        if sort_columns:  # canonical CSR; the steps themselves do not need it
            out_col[base : base + kept].sort()
        # Normalise again, accumulate P^(k)(i) and the next step's products for this row;
        # acc then holds the row of F^(k).
        new_sum = 0.0
        cost = 0
        inverse = 1.0 / scaled_total
        if points.shape[1] == 3:  # positions: the three sums in registers, in the same pass
            moved_x = moved_y = moved_z = 0.0
            for t in range(kept):
                c = _U(out_col[_U(base + t)])
                value = acc[c] * inverse
                acc[c] = value
                out_val[_U(base + t)] = value
                new_sum += value
                cost += w_crow[c + _U(1)] - w_crow[c] + 1
                moved_x += value * points[c, 0]
                moved_y += value * points[c, 1]
                moved_z += value * points[c, 2]
            new_points[target, 0] = moved_x
            new_points[target, 1] = moved_y
            new_points[target, 2] = moved_z
        else:  # any other number of channels: one at a time, after the row
            for t in range(kept):
                c = _U(out_col[_U(base + t)])
                value = acc[c] * inverse
                acc[c] = value
                out_val[_U(base + t)] = value
                new_sum += value
                cost += w_crow[c + _U(1)] - w_crow[c] + 1
            for d in range(points.shape[1]):
                moved = 0.0
                for t in range(kept):
                    moved += out_val[_U(base + t)] * points[_U(out_col[_U(base + t)]), d]
                new_points[target, d] = moved
        # D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j): the new row's sum, corrected on the
        # columns of the old row by |new - old| - new (new = 0 where a column was dropped).
        difference = new_sum
        for e in range(first, last):
            now = acc[_U(f_col[_U(e)])]
            difference += abs(now - f_val[_U(e)]) - now
        for t in range(kept):
            acc[_U(out_col[_U(base + t)])] = 0.0
        return kept, difference, cost

    @njit(cache=True, parallel=True, nogil=True)
    def _parts(
        part_first, part_last, region_start, region_end, products, f_start, f_count, f_col,
        f_val, diagonal, w_crow, w_col, w_val, row_sums, alpha, threshold, points, sort_columns,
        acc, out_col, out_val, out_start, out_count, differences, new_points, row_target, costs,
        stopped,
    ):  # fmt: skip
        """Rows ``[part_first[p], part_last[p])`` into ``out_*[region_start[p]:region_end[p]]``.

        The difference and moved point of row ``i`` go to row ``row_target[i]`` of
        ``differences`` and ``new_points``.

        ``acc`` holds ``(threads, V)`` zeroed scratch rows, one per thread. A row has at most
        ``min(products[i], V)`` columns; one whose bound does not fit the rest of its region
        is computed aside and copied in if it fits; otherwise the part stops and
        ``stopped[p]`` is the first row not done (``part_last[p]`` when the part completed).
        """
        num_cols = acc.shape[1]
        for part in prange(part_first.shape[0]):
            thread_acc = acc[numba.get_thread_id()]  # a view taken once per part
            widest = 0
            for i in range(part_first[part], part_last[part]):
                widest = max(widest, min(products[i], num_cols))
            touched = np.empty(widest + 1, dtype=np.int64)
            aside_col = np.empty(widest, dtype=out_col.dtype)
            aside_val = np.empty(widest, dtype=out_val.dtype)
            cursor, end = region_start[part], region_end[part]
            stopped[part] = part_last[part]
            for i in range(part_first[part], part_last[part]):
                fits = cursor + min(products[i], num_cols) <= end
                # One call site, so that the inlined row is compiled once.
                row_col, row_val = (out_col, out_val) if fits else (aside_col, aside_val)
                kept, difference, cost = _row(
                    i, f_start, f_count, f_col, f_val, diagonal, w_crow, w_col, w_val,
                    row_sums, alpha, threshold, points, sort_columns, thread_acc, touched,
                    row_col, row_val, cursor if fits else 0, new_points, row_target[i],
                )  # fmt: skip
                if not fits:
                    if cursor + kept > end:
                        stopped[part] = i
                        break
                    out_col[cursor : cursor + kept] = aside_col[:kept]
                    out_val[cursor : cursor + kept] = aside_val[:kept]
                out_start[i] = cursor
                out_count[i] = kept
                differences[row_target[i]] = difference
                costs[i] = cost
                cursor += kept

    @njit(cache=True, nogil=True)
    def _regions(part_first, part_last, counts, products, num_cols, factor, used):
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

    @njit(cache=True, parallel=True, nogil=True)
    def _gather_rows(starts, counts, col, val, crow, out_col, out_val):
        """Copy the rows of a gapped CSR back to back at ``crow`` (a packed CSR)."""
        for i in prange(starts.shape[0]):
            source, size = starts[i], counts[i]
            out_col[crow[i] : crow[i] + size] = col[source : source + size]
            out_val[crow[i] : crow[i] + size] = val[source : source + size]

    @njit(cache=True, nogil=True)
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

    @njit(cache=True, parallel=True, nogil=True)
    def _products(f_start, f_count, f_col, w_crow):
        """``(n,)`` scalar products each row of ``F @ Lhat`` costs (``W`` plus the diagonal)."""
        products = np.zeros(f_start.shape[0], dtype=np.int64)
        for i in prange(f_start.shape[0]):
            total = 0
            for e in range(f_start[i], f_start[i] + f_count[i]):
                total += w_crow[f_col[e] + 1] - w_crow[f_col[e]] + 1
            products[i] = total
        return products


@dataclass(frozen=True)
class SplitLhat:
    """``Lhat = diag(diagonal) + W`` in the form the kernel reads.

    Attributes:
        diagonal: ``(V,)`` float.
        w_crow, w_col, w_val: ``W`` (``Lhat`` without its diagonal) in CSR form.
        row_sums: ``(V,)`` row sums of ``Lhat``.
    """

    diagonal: np.ndarray
    w_crow: np.ndarray
    w_col: np.ndarray
    w_val: np.ndarray
    row_sums: np.ndarray

    @classmethod
    def from_csr(cls, crow: np.ndarray, col: np.ndarray, val: np.ndarray) -> SplitLhat:
        """Split ``Lhat`` given in CSR form (every row holds its diagonal entry)."""
        return cls(*_split_diagonal(crow, col, val))

    @property
    def num_cols(self) -> int:
        return int(self.diagonal.shape[0])


def first_rows(
    crow: np.ndarray, col: np.ndarray, val: np.ndarray, lhat: SplitLhat,
    rows: np.ndarray | None = None, index=np.int64,
) -> Rows:  # fmt: skip
    """Rows of ``F^(1)``, ``Lhat`` normalised by rows, packed with ``index`` column indices.

    Args:
        crow, col, val: ``Lhat`` in CSR form.
        lhat: the same ``Lhat`` split (its ``row_sums`` divide the rows).
        rows: ``(R,)`` int64 rows to take, in that order (default: all).
        index: column index dtype of the result.
    """
    if rows is None:
        rows, size = np.arange(crow.shape[0] - 1, dtype=np.int64), int(crow[-1] - crow[0])
    else:
        size = int((crow[rows + 1] - crow[rows]).sum())
    out_col = np.empty(size, dtype=index)
    out_crow, out_val = _normalised_rows(crow, col, val, lhat.row_sums, rows, out_col)
    return Rows.from_csr(out_crow, out_col, out_val)


@dataclass
class Rows:
    """A CSR matrix whose rows may be separated by unused entries.

    Row ``i`` is ``col[starts[i] : starts[i] + counts[i]]`` (and the same slice of ``val``).

    Attributes:
        starts, counts: ``(n,)`` int64.
        col: ``(capacity,)`` int32 or int64 column indices.
        val: ``(capacity,)`` float values.
        costs: ``(n,)`` int64 scalar products each row costs in the next step, or ``None``.
    """

    starts: np.ndarray
    counts: np.ndarray
    col: np.ndarray
    val: np.ndarray
    costs: np.ndarray | None = None

    @classmethod
    def from_csr(cls, crow: np.ndarray, col: np.ndarray, val: np.ndarray) -> Rows:
        """View a packed CSR ``(crow, col, val)``."""
        return cls(crow[:-1], np.diff(crow), col, val)

    @property
    def num_rows(self) -> int:
        return int(self.starts.shape[0])

    @property
    def nnz(self) -> int:
        return int(self.counts.sum())

    def to_csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(crow, col, val)``: the rows packed into fresh arrays."""
        crow = np.zeros(self.num_rows + 1, dtype=np.int64)
        np.cumsum(self.counts, out=crow[1:])
        col = np.empty(crow[-1], dtype=self.col.dtype)
        val = np.empty(crow[-1], dtype=self.val.dtype)
        _gather_rows(self.starts, self.counts, self.col, self.val, crow, col, val)
        return crow, col, val


def prefaulted_zeros(shape, dtype) -> np.ndarray:
    """``np.zeros(shape, dtype)`` with every page written here, by the calling thread.

    The parallel kernel writes its outputs and buffers from several threads; a page touched
    for the first time there costs far more than from one thread (about 20 us against 1.5 us
    per 4 KiB page on the 2-core virtual machines measured here: a 2.6M-vertex run went from
    11-12 s to 7.6 s of steps, plus 0.3 s for this). numpy also asks the OS for transparent
    huge pages for arrays of 4 MiB or more.
    """
    array = np.empty(shape, dtype=dtype)
    array.fill(0)
    return array


class Workspace:
    """Buffers that consecutive steps of a run reuse instead of allocating afresh.

    Touching freshly allocated pages costs time (on virtual machines that hand freed memory
    back to the host, up to as much as the arithmetic of a step), so a run keeps its scratch
    rows and two output buffers (with their row arrays) that the steps use in turn. The
    :class:`Rows` a step returns live in one output buffer and are overwritten by the step
    after next: hold at most the current and the previous operator. Between runs, idle
    workspaces wait in :data:`WORKSPACES`.

    Args:
        num_cols: ``V``, the number of columns of ``F``.
        dtype: value dtype.
        capacity: expected stored entries of the largest output (grown when exceeded).
        index_dtype: column index dtype of the outputs (that of the input rows).
    """

    def __init__(self, num_cols: int, dtype, capacity: int = 0, index_dtype=np.int64):
        self.dtype, self.index_dtype = np.dtype(dtype), np.dtype(index_dtype)
        self.outputs = [
            (prefaulted_zeros(capacity, self.index_dtype), prefaulted_zeros(capacity, self.dtype))
            for _ in range(2)
        ]
        self.acc = np.zeros(0, dtype=self.dtype)  # flat, so that any (threads, V) view fits
        self.rows = [np.empty((3, 0), dtype=np.int64) for _ in range(2)]
        self.start(num_cols, capacity)

    def start(self, num_cols: int, capacity: int) -> None:
        """Prepare for a run on ``num_cols`` columns with outputs of ``capacity`` entries."""
        self.num_cols, self.turn = num_cols, 0
        self.outputs = [
            (_grow(col, 0, capacity), _grow(val, 0, capacity)) for col, val in self.outputs
        ]

    @property
    def nbytes(self) -> int:
        """Bytes held by the output buffers and the scratch rows."""
        buffers = sum(col.nbytes + val.nbytes for col, val in self.outputs)
        return buffers + self.acc.nbytes + sum(rows.nbytes for rows in self.rows)

    def scratch(self, threads: int) -> np.ndarray:
        """``(threads, V)`` zero rows (the kernel leaves them zero when a step ends)."""
        size = threads * self.num_cols
        if self.acc.shape[0] < size:
            self.acc = prefaulted_zeros(size, self.dtype)
        return self.acc[:size].reshape(threads, self.num_cols)

    def next_output(self) -> tuple[np.ndarray, np.ndarray]:
        """The output buffer pair whose contents are two steps old."""
        self.turn ^= 1
        return self.outputs[self.turn]

    def row_arrays(self, num_rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(starts, counts, costs)``: ``(num_rows,)`` int64 arrays (not zeroed) that go with
        the output buffer pair of :meth:`next_output`."""
        if self.rows[self.turn].shape[1] < num_rows:
            self.rows[self.turn] = prefaulted_zeros((3, num_rows), np.int64)
        starts, counts, costs = self.rows[self.turn][:, :num_rows]
        return starts, counts, costs

    def keep_output(self, col: np.ndarray, val: np.ndarray) -> None:
        """Remember a buffer pair that a step had to grow."""
        self.outputs[self.turn] = (col, val)


class WorkspacePool:
    """Idle :class:`Workspace` objects kept between runs, at most ``max_bytes`` in all.

    A training loop or a benchmark runs the steps on mesh after mesh; taking the buffers of
    the previous run saves allocating and touching tens of megabytes each time. A workspace
    is lent to one run at a time (threads that run meshes concurrently get different ones).
    Workspaces larger than ``max_bytes`` are never kept, so large meshes hold no memory
    after their run.

    Args:
        max_bytes: upper bound on the bytes kept idle; ``0`` keeps nothing.
    """

    def __init__(self, max_bytes: int):
        self.max_bytes = max_bytes
        self._idle: list[Workspace] = []
        self._lock = threading.Lock()

    @property
    def idle_bytes(self) -> int:
        """Bytes held by the idle workspaces."""
        with self._lock:
            return sum(workspace.nbytes for workspace in self._idle)

    @contextmanager
    def borrow(self, num_cols: int, dtype, capacity: int, index_dtype) -> Iterator[Workspace]:
        """A workspace for one run, taken from the idle ones when one has these dtypes."""
        wanted = (np.dtype(dtype), np.dtype(index_dtype))
        with self._lock:
            found = next(
                (w for w in reversed(self._idle) if (w.dtype, w.index_dtype) == wanted), None
            )
            if found is not None:
                self._idle.remove(found)
        if found is None:
            workspace = Workspace(num_cols, dtype, capacity, index_dtype)
        else:
            workspace = found
            workspace.start(num_cols, capacity)
        try:
            yield workspace
        finally:
            self._give_back(workspace)

    def _give_back(self, workspace: Workspace) -> None:
        with self._lock:
            self._idle.append(workspace)
            total = sum(w.nbytes for w in self._idle)
            while self._idle and total > self.max_bytes:
                total -= self._idle.pop(0).nbytes  # the oldest first

    def clear(self) -> None:
        """Free every idle workspace."""
        with self._lock:
            self._idle.clear()


#: The process-wide pool the diffusion runs borrow their workspaces from. Set
#: ``WORKSPACES.max_bytes = 0`` to keep nothing between runs.
WORKSPACES = WorkspacePool(DEFAULT_POOL_BYTES)


def _grow(array: np.ndarray, used: int, needed: int) -> np.ndarray:
    """``array`` if it holds ``needed`` entries, else a larger copy of its first ``used``."""
    if needed <= array.shape[0]:
        return array
    larger = prefaulted_zeros(max(needed, int(1.25 * array.shape[0])), array.dtype)
    larger[:used] = array[:used]
    return larger




def fused_step(
    previous: Rows, lhat: SplitLhat, alpha: np.ndarray, threshold: float,
    points: np.ndarray, num_threads: int, sort_columns: bool = True,
    workspace: Workspace | None = None, growth: float | None = None,
    row_target: np.ndarray | None = None, differences: np.ndarray | None = None,
    new_points: np.ndarray | None = None,
) -> tuple[Rows, np.ndarray, np.ndarray]:  # fmt: skip
    """One diffusion step on CPU arrays.

    Args:
        previous: ``F^(k-1)``, ``n`` rows (see :meth:`Rows.from_csr`).
        lhat: ``Lhat``, ``(V, V)`` (see :meth:`SplitLhat.from_csr`).
        alpha: ``(V,)`` scale invariance function.
        threshold: ``lambda``.
        points: ``(V, C)`` positions ``P`` (any number of channels).
        num_threads: threads to use.
        sort_columns: sort the columns within each row (canonical CSR). The steps do not need
            it, so the diffusion loop skips it unless the operators are returned.
        workspace: reuse its buffers (the returned rows then live in them, see
            :class:`Workspace`); ``None`` allocates fresh arrays.
        growth: expected ratio of output to input entries per row (default
            :data:`DEFAULT_GROWTH`); it sizes the first round's output regions. Rows that do
            not fit are redone, so it affects speed and memory, never the result.
        row_target: ``(n,)`` int64 row of ``differences`` and ``new_points`` that each row's
            results go to (default: the same row); lets a run in a renumbered vertex order
            write its results in the caller's order.
        differences, new_points: ``(m,)`` and ``(m, C)`` output arrays to fill (default: new
            arrays with ``m = n``).

    Returns:
        ``(F^(k), D^(k), F^(k) P)``: :class:`Rows` (with ``costs``), the difference map and
        the moved points.
    """
    if numba is None:
        raise RuntimeError("the fused kernel needs numba: pip install numba")
    growth = DEFAULT_GROWTH if growth is None else growth
    # Small steps run on one thread: waking the pool costs more than it saves.
    wanted = 1 if previous.nnz < SERIAL_ENTRIES else num_threads
    numba.set_num_threads(max(1, min(wanted, numba.config.NUMBA_NUM_THREADS)))
    threads = numba.get_num_threads()
    num_rows, num_cols = previous.num_rows, lhat.num_cols
    if workspace is None:
        workspace = Workspace(num_cols, previous.val.dtype, index_dtype=previous.col.dtype)
    acc = workspace.scratch(threads)
    products = previous.costs
    if products is None:
        products = _products(previous.starts, previous.counts, previous.col, lhat.w_crow)

    dtype = previous.val.dtype
    if row_target is None:
        row_target = np.arange(num_rows, dtype=np.int64)
    if differences is None:
        differences = np.zeros(num_rows, dtype=dtype)
    if new_points is None:
        new_points = np.zeros((num_rows, points.shape[1]), dtype=dtype)
    col, val = workspace.next_output()
    out_start, out_count, costs = workspace.row_arrays(num_rows)  # every row is written
    first, last = _balanced_parts(products, PARTS_PER_THREAD * threads)
    used = 0
    for attempt in range(_ESTIMATED_ROUNDS + 1):
        factor = growth * 2**attempt if attempt < _ESTIMATED_ROUNDS else -1.0
        start, end = _regions(first, last, previous.counts, products, num_cols, factor, used)
        needed = int(end[-1]) if end.size else used
        col, val = _grow(col, used, needed), _grow(val, used, needed)
        stopped = np.empty_like(first)
        _run_dynamic(
            _parts, first, last, start, end, products, previous.starts, previous.counts,
            previous.col, previous.val, lhat.diagonal, lhat.w_crow, lhat.w_col, lhat.w_val,
            lhat.row_sums, alpha, threshold, points, sort_columns, acc, col, val, out_start,
            out_count, differences, new_points, row_target, costs, stopped,
        )  # fmt: skip
        used = needed
        unfinished = stopped < last
        if not unfinished.any():
            break
        logger.debug(
            "%d row ranges overflowed their estimated regions (round %d)",
            int(unfinished.sum()), attempt,
        )  # fmt: skip
        first, last = stopped[unfinished], last[unfinished]
    workspace.keep_output(col, val)
    return Rows(out_start, out_count, col, val, costs), differences, new_points


def index_dtype(num_cols: int) -> type:
    """``np.int32`` when it can index ``num_cols`` columns, else ``np.int64``.

    The steps read and write every stored column index, so 4-byte indices save a quarter of
    the memory traffic and footprint of ``F`` in float64 (a third in float32).
    """
    return np.int32 if num_cols <= np.iinfo(np.int32).max else np.int64


def growth_from_entries(entries_per_row: list[float], step: int, slack: float = 1.15) -> float:
    """Output room per input entry for step ``step`` (``2..K``) from estimated row lengths."""
    if step - 1 >= len(entries_per_row) or entries_per_row[step - 2] <= 0:
        return DEFAULT_GROWTH
    ratio = entries_per_row[step - 1] / entries_per_row[step - 2]
    return max(1.0, ratio) * slack if math.isfinite(ratio) else DEFAULT_GROWTH


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

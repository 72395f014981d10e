"""The drivers of the compiled step kernel: whole steps (:func:`fused_step`) and rows streamed
through every step (:func:`stream_steps`, no operator stored).

A whole step writes each row range into an output region sized from ``growth`` times its
input row lengths; a block that does not fit stops its range, which a later round redoes with
larger regions (the last round's cannot overflow). The result is a CSR whose rows may be
separated by gaps (:class:`~.rows.Rows`), so no step copies its output.
"""

from __future__ import annotations

import logging
from typing import NamedTuple

import numpy as np

from .._common.errors import ParameterError
from .block import LANES, BlockResults, BlockScratch, RowArrays, SplitLhat, StepInputs, row_width
from .buffers import Workspace, grown
from .jit import kernel_jit
from .rows import Rows, step_costs
from .threads import kernel_thread_count, numba_available, run_workers

if numba_available():
    from numba import njit

    from .block import _block, _first_row
    from .threads import next_part

logger = logging.getLogger(__name__)

#: Row ranges per thread, handed out dynamically.
PARTS_PER_THREAD = 32
#: Below this many entries of ``F^(k-1)`` a step runs on one thread (starting threads would
#: cost more than they save).
SERIAL_ENTRIES = 1 << 18
#: Below this many rows of ``F`` a streamed run (:func:`stream_steps`) uses one thread.
SERIAL_ROWS = 1 << 13
#: Output room per input entry when nothing better is known (a first step grows ~3x).
DEFAULT_GROWTH = 3.0
#: Rounds with estimated regions before the last, overflow-free one.
_ESTIMATED_ROUNDS = 3


class _Regions(NamedTuple):
    """Row ranges ``[first, last)`` of whole blocks and their output regions ``[start, end)``."""

    first: np.ndarray
    last: np.ndarray
    start: np.ndarray
    end: np.ndarray


class _StepOutput(NamedTuple):
    """A whole step's gapped CSR and, per row, ``D^(k)``, ``F^(k) P`` and the next step's cost."""

    col: np.ndarray
    val: np.ndarray
    start: np.ndarray
    count: np.ndarray
    differences: np.ndarray
    moved: np.ndarray
    costs: np.ndarray


class _StreamOutput(NamedTuple):
    """Where :func:`_stream_worker` writes: ``(K, m)`` differences, ``(K, m, C)`` positions at
    row ``row_target[i]`` for row ``i``, and ``(parts, K)`` entry counts."""

    row_target: np.ndarray
    differences: np.ndarray
    positions: np.ndarray
    entries: np.ndarray


if numba_available():

    @njit(nogil=True, inline="always")
    def _thread_scratch(acc, weights, marks, thread, inputs, touched, stage_col, stage_val, width):
        """The :class:`BlockScratch` of thread ``thread`` (rows of the shared scratch)."""
        num_cols = marks.shape[1] // 2
        return BlockScratch(
            acc[thread],
            weights[thread],
            marks[thread, :num_cols],
            marks[thread, num_cols:],
            inputs,
            touched,
            stage_col,
            stage_val,
            width,
        )

    @kernel_jit(nogil=True)
    def _step_worker(
        thread, counter, parts, products, rows, lhat, step, scratch_rows, out, stopped
    ):
        """Rows ``[parts.first[p], parts.last[p])`` into ``out.col/val[parts.start[p]:
        parts.end[p]]`` for the ranges ``p`` taken from ``counter``, in blocks of ``LANES``
        rows, on row ``thread`` of the ``scratch_rows`` (:meth:`.Workspace.scratch`). A block
        that does not fit the rest of its region stops its part: ``stopped[p]`` is its first
        row (``parts.last[p]`` when the part completed)."""
        acc, weights, marks = scratch_rows
        num_cols = lhat.diagonal.shape[0]
        channels = step.points.shape[1]
        while True:
            part = next_part(counter)
            if part >= parts.first.shape[0]:
                break
            first, last = parts.first[part], parts.last[part]
            width, block_width, block_inputs = 0, 0, 0
            for start in range(first, last, LANES):
                block_products, inputs = 0, 0
                for i in range(start, min(start + LANES, last)):
                    width = max(width, min(products[i], num_cols))
                    block_products += products[i]
                    inputs += rows.count[i]
                block_width = max(block_width, min(block_products, num_cols))
                block_inputs = max(block_inputs, inputs)
            scratch = _thread_scratch(
                acc,
                weights,
                marks,
                thread,
                np.empty(block_inputs + 1, dtype=np.int64),
                np.empty(block_width + 1, dtype=np.int64),
                np.empty(LANES * (width + 1), dtype=out.col.dtype),
                np.empty(LANES * (width + 1), dtype=out.val.dtype),
                width,
            )
            results = BlockResults(
                np.zeros(LANES, dtype=np.int64),
                np.zeros(LANES, dtype=out.val.dtype),
                np.zeros(LANES, dtype=np.int64),
                np.zeros((LANES, channels), dtype=out.val.dtype),
            )
            cursor, end = parts.start[part], parts.end[part]
            stopped[part] = last
            for first_row in range(first, last, LANES):
                lanes = min(LANES, last - first_row)
                _block(first_row, lanes, rows, lhat, step, scratch, results)
                if cursor + results.kept[:lanes].sum() > end:
                    stopped[part] = first_row
                    break
                for b in range(lanes):
                    i = first_row + b
                    size = results.kept[b]
                    o = b * (width + 1)
                    out.col[cursor : cursor + size] = scratch.stage_col[o : o + size]
                    out.val[cursor : cursor + size] = scratch.stage_val[o : o + size]
                    out.start[i] = cursor
                    out.count[i] = size
                    out.differences[i] = results.differences[b]
                    out.costs[i] = results.costs[b]
                    out.moved[i] = results.moved[b]
                    cursor += size

    @kernel_jit(nogil=True)
    def _stream_worker(thread, counter, first, last, lhat, step, width, scratch_rows, out):
        """Rows ``[first[p], last[p])`` for the ranges ``p`` taken from ``counter``, a block of
        ``LANES`` rows at a time from ``F^(1)`` to ``F^(K)`` in two staging buffers of
        ``width`` entries a row; ``out.entries[p, k]`` counts the entries of ``F^(k + 1)``."""
        acc, weights, marks = scratch_rows
        num_cols = lhat.diagonal.shape[0]
        num_scales = out.differences.shape[0]
        channels = step.points.shape[1]
        stride = width + 1
        old_col = np.empty(LANES * stride, dtype=lhat.w_col.dtype)
        old_val = np.empty(LANES * stride, dtype=lhat.w_val.dtype)
        new_col, new_val = np.empty_like(old_col), np.empty_like(old_val)
        inputs = np.empty(min(num_cols, LANES * width) + 1, dtype=np.int64)
        touched = np.empty(num_cols + 1, dtype=np.int64)
        offsets = np.arange(LANES) * stride
        old_count = np.zeros(LANES, dtype=np.int64)
        new_count = np.zeros(LANES, dtype=np.int64)
        differences = np.zeros(LANES, dtype=lhat.w_val.dtype)
        costs = np.zeros(LANES, dtype=np.int64)
        moved = np.zeros((LANES, channels), dtype=lhat.w_val.dtype)
        while True:
            part = next_part(counter)
            if part >= first.shape[0]:
                break
            for first_row in range(first[part], last[part], LANES):
                lanes = min(LANES, last[part] - first_row)
                old_count[:] = 0
                for b in range(lanes):
                    old_count[b] = _first_row(
                        first_row + b, lhat, old_col[offsets[b] :], old_val[offsets[b] :]
                    )
                for k in range(1, num_scales):
                    rows = RowArrays(offsets, old_count, old_col, old_val)
                    scratch = _thread_scratch(
                        acc, weights, marks, thread, inputs, touched, new_col, new_val, width
                    )
                    results = BlockResults(new_count, differences, costs, moved)
                    _block(0, lanes, rows, lhat, step, scratch, results)
                    for b in range(lanes):
                        target = out.row_target[first_row + b]
                        out.differences[k, target] = differences[b]
                        out.positions[k, target] = moved[b]
                        out.entries[part, k] += new_count[b]
                    old_col, new_col = new_col, old_col
                    old_val, new_val = new_val, old_val
                    old_count, new_count = new_count, old_count


def _regions(first, last, counts, products, num_cols, factor, used):
    """Back-to-back ``[start, end)`` output regions of the parts, from ``used`` on: room for
    ``ceil(factor * counts[i]) + 2`` entries of row ``i``, at most ``min(products[i], V)``,
    which ``factor < 0`` gives every row (a round that cannot overflow)."""
    room = np.minimum(products, num_cols)
    if factor >= 0:
        room = np.minimum(room, np.ceil(factor * counts).astype(np.int64) + 2)
    cumulative = np.concatenate([[0], np.cumsum(room)])
    sizes = cumulative[last] - cumulative[first]
    end = used + np.cumsum(sizes)
    return end - sizes, end


def _balanced_parts(work: np.ndarray, parts: int) -> tuple[np.ndarray, np.ndarray]:
    """Split rows ``[0, n)`` into at most ``parts`` ranges ``[first, last)`` of about equal
    ``work``: a range ends before the row whose running total first exceeds the next
    ``p / parts`` of the total (empty ranges dropped)."""
    if not work.size:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    cumulative = np.cumsum(work)
    inner = np.searchsorted(cumulative, cumulative[-1] * np.arange(1, parts) / parts, "right")
    bounds = np.unique(np.concatenate([[0], inner, [work.shape[0]]]))
    return bounds[:-1], bounds[1:]


def block_parts(
    block_work: np.ndarray, start: int, stop: int, parts: int
) -> tuple[np.ndarray, np.ndarray]:
    """Rows ``[start, stop)`` (``start`` a multiple of :data:`LANES`) in at most ``parts``
    ranges ``[first, last)`` of whole blocks and about equal work (``block_work``, one value
    per block of the range), so that a row's block never depends on the split."""
    first, last = _balanced_parts(block_work, parts)
    return start + first * LANES, np.minimum(start + last * LANES, stop)


def fused_step(
    previous: Rows,
    lhat: SplitLhat,
    alpha: np.ndarray,
    threshold: float,
    points: np.ndarray,
    num_threads: int,
    sort_columns: bool = True,
    workspace: Workspace | None = None,
    growth: float | None = None,
) -> tuple[Rows, np.ndarray, np.ndarray]:
    """One diffusion step on CPU arrays.

    Args:
        previous: ``F^(k-1)``, ``n`` rows.
        lhat: ``Lhat``, ``(V, V)`` (:func:`~.rows.split_lhat`).
        alpha: ``(V,)`` scale invariance function.
        threshold: ``lambda``.
        points: ``(V, C)`` positions ``P`` (any number of channels).
        num_threads: threads to use (one below :data:`SERIAL_ENTRIES` entries).
        sort_columns: sort the columns within each row (canonical CSR).
        workspace: lends its buffers, in which the returned rows then live; default: fresh.
        growth: expected ratio of output to input entries per row (default
            :data:`DEFAULT_GROWTH`), the first round's room: speed and memory, never results.

    Returns:
        ``(F^(k), D^(k), F^(k) P)``: :class:`~.rows.Rows` (with ``costs``), the ``(n,)``
        difference map and the ``(n, C)`` moved points.
    """
    growth = DEFAULT_GROWTH if growth is None else growth
    num_rows, num_cols = previous.num_rows, lhat.num_cols
    dtype = previous.val.dtype
    if workspace is None:
        workspace = Workspace(num_cols, dtype, index_dtype=previous.col.dtype)
    products = step_costs(previous, lhat)
    step = StepInputs(alpha, float(threshold), points, bool(sort_columns), count_costs=True)
    threads = kernel_thread_count(1 if previous.nnz < SERIAL_ENTRIES else num_threads)
    scratch_rows = workspace.scratch(threads, LANES)
    col, val, start, count, costs = workspace.next_output(num_rows)  # every row is written
    differences = np.zeros(num_rows, dtype=dtype)
    moved = np.zeros((num_rows, points.shape[1]), dtype=dtype)
    block_work = np.add.reduceat(products, np.arange(0, num_rows, LANES)) if num_rows else products
    first, last = block_parts(block_work, 0, num_rows, PARTS_PER_THREAD * threads)
    used = 0
    for attempt in range(_ESTIMATED_ROUNDS + 1):
        factor = growth * 2**attempt if attempt < _ESTIMATED_ROUNDS else -1.0
        region_start, region_end = _regions(
            first, last, previous.counts, products, num_cols, factor, used
        )
        needed = int(region_end[-1]) if region_end.size else used
        col, val = grown(col, used, needed), grown(val, used, needed)
        stopped = np.empty_like(first)
        run_workers(
            _step_worker,
            min(threads, max(first.shape[0], 1)),
            np.zeros(1, dtype=np.int64),
            _Regions(first, last, region_start, region_end),
            products,
            RowArrays(previous.starts, previous.counts, previous.col, previous.val),
            lhat,
            step,
            scratch_rows,
            _StepOutput(col, val, start, count, differences, moved, costs),
            stopped,
        )
        used = needed
        unfinished = stopped < last
        if not unfinished.any():
            break
        logger.debug("%d row ranges overflowed their regions (round %d)", unfinished.sum(), attempt)
        first, last = stopped[unfinished], last[unfinished]
    workspace.keep_output(col, val)
    return Rows(start, count, col, val, costs), differences, moved


def stream_steps(
    lhat: SplitLhat,
    alpha: np.ndarray,
    threshold: float,
    points: np.ndarray,
    num_threads: int,
    rows: tuple[int, int],
    differences: np.ndarray,
    positions: np.ndarray,
    row_target: np.ndarray | None = None,
    workspace: Workspace | None = None,
) -> np.ndarray:
    """Steps ``2..K`` for the rows ``[rows[0], rows[1])``, each block of rows from ``F^(1)``
    through every step before the next: no operator is held (memory ``O(threads V)``).

    Args:
        lhat, alpha, threshold, points, num_threads: as for :func:`fused_step` (one thread
            below :data:`SERIAL_ROWS` rows); the results take the dtype of ``lhat``'s values.
        rows: the row range; its start must be a multiple of :data:`~.block.LANES` (row
            blocks, and so the results, must not depend on how a run is split).
        differences, positions: ``(K, m)`` and ``(K, m, C)`` outputs; ``D^(k)`` and
            ``P^(k)`` of row ``i`` go to row ``row_target[i]`` (default ``i``) of index
            ``k - 1``; index 0 is not written.
        workspace: lends its scratch rows (default: a fresh one).

    Returns:
        ``(K - 1,)`` int64: the stored entries of ``F^(2..K)`` in these rows.
    """
    start, stop = rows
    num_rows = lhat.num_cols
    if not 0 <= start <= stop <= num_rows:
        raise ParameterError(f"row range {rows} is not within the {num_rows} rows")
    if start % LANES:
        raise ParameterError(f"a row range must start at a multiple of {LANES}, not {start}")
    if workspace is None:
        workspace = Workspace(num_rows, lhat.w_val.dtype, index_dtype=lhat.w_col.dtype)
    if row_target is None:
        row_target = np.arange(num_rows, dtype=np.int64)
    # Block starts and ends; the row lengths of F^(1) (W's and the diagonal) stand in for
    # the work of a row through every step.
    blocks = np.arange(start, stop + LANES, LANES)
    blocks[-1] = stop
    block_work = np.diff(lhat.w_crow[blocks] + blocks)
    longest = int(np.diff(lhat.w_crow[start : stop + 1]).max()) + 1 if stop > start else 0
    width = row_width(num_rows, longest, threshold)
    step = StepInputs(alpha, float(threshold), points, sort_columns=False, count_costs=False)
    threads = kernel_thread_count(1 if num_rows < SERIAL_ROWS else num_threads)
    first, last = block_parts(block_work, start, stop, PARTS_PER_THREAD * threads)
    entries = np.zeros((first.shape[0], differences.shape[0]), dtype=np.int64)
    run_workers(
        _stream_worker,
        min(threads, max(first.shape[0], 1)),
        np.zeros(1, dtype=np.int64),
        first,
        last,
        lhat,
        step,
        width,
        workspace.scratch(threads, LANES),
        _StreamOutput(row_target, differences, positions, entries),
    )
    return entries.sum(axis=0)[1:]

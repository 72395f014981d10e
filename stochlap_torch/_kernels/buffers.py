"""Buffers of the numba kernels: pre-touched arrays, and workspaces reused from step to step
and kept between runs."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from .jit import kernel_jit
from .threads import kernel_thread_count, numba_available, run_workers

if numba_available():
    from .threads import next_part

#: Bytes of idle workspaces kept between runs (see :class:`WorkspacePool`).
DEFAULT_POOL_BYTES = 256 * 2**20
#: Arrays at least this large are pre-touched by several threads (:func:`prefaulted_zeros`).
PARALLEL_FILL_BYTES = 32 * 2**20
#: Bytes one thread zeroes at a time in a parallel fill (whole huge pages).
_FILL_RUN = 2 * 2**20


if numba_available():

    @kernel_jit(nogil=True)
    def _fill_worker(thread, counter, data):
        """Zero the bytes ``data``, a run of whole pages at a time, taken from ``counter``."""
        size = data.shape[0]
        runs = (size + _FILL_RUN - 1) // _FILL_RUN
        while True:
            run = next_part(counter)
            if run >= runs:
                break
            data[run * _FILL_RUN : min(size, (run + 1) * _FILL_RUN)] = 0


def prefaulted_zeros(shape, dtype, threads: int = 1) -> np.ndarray:
    """``np.zeros(shape, dtype)`` with every page written before any kernel runs (a page first
    touched inside the parallel kernel costs far more, above all on virtual machines, which
    give memory faster to several threads: ``threads`` fill arrays of
    :data:`PARALLEL_FILL_BYTES` or more)."""
    array = np.empty(shape, dtype=dtype)
    if threads > 1 and array.nbytes >= PARALLEL_FILL_BYTES and numba_available():
        counter = np.zeros(1, dtype=np.int64)
        run_workers(
            _fill_worker, kernel_thread_count(threads), counter, array.reshape(-1).view(np.uint8)
        )
    else:
        array.fill(0)
    return array


class Workspace:
    """Buffers that consecutive steps of a run reuse: the scratch rows and, for whole steps,
    two output buffers used in turn, so the :class:`~.rows.Rows` a step returns are
    overwritten by the step after next (hold at most the current and the previous operator).
    ``num_cols`` is ``V``; ``capacity`` the expected entries of the largest output (grown when
    exceeded); ``index_dtype`` that of the input rows' columns."""

    def __init__(self, num_cols: int, dtype, capacity: int = 0, index_dtype=np.int64):
        self.dtype, self.index_dtype = np.dtype(dtype), np.dtype(index_dtype)
        self.outputs = [(np.zeros(0, self.index_dtype), np.zeros(0, self.dtype))] * 2
        # Flat, so that any (threads, V * lanes) view fits.
        self.acc = self.weights = np.zeros(0, dtype=self.dtype)
        self.marks = np.zeros(0, dtype=np.uint8)
        self.rows = [np.empty((3, 0), dtype=np.int64) for _ in range(2)]
        self.start(num_cols, capacity)

    def start(self, num_cols: int, capacity: int) -> None:
        """Prepare for a run (arguments as for the constructor)."""
        self.num_cols, self.turn = num_cols, 0
        self.outputs = [
            (grown(col, 0, capacity), grown(val, 0, capacity)) for col, val in self.outputs
        ]

    @property
    def nbytes(self) -> int:
        """Bytes held by the output buffers and the scratch rows."""
        buffers = sum(col.nbytes + val.nbytes for col, val in self.outputs)
        scratch = self.acc.nbytes + self.weights.nbytes + self.marks.nbytes
        return buffers + scratch + sum(rows.nbytes for rows in self.rows)

    def scratch(self, threads: int, lanes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(acc, weights, marks)``: ``(threads, V * lanes)`` float and ``(threads, 2 V)``
        uint8 zero rows (the kernel leaves them zero when a step ends)."""
        size = threads * self.num_cols * lanes
        if self.acc.shape[0] < size:
            self.acc = prefaulted_zeros(size, self.dtype, threads)
            self.weights = prefaulted_zeros(size, self.dtype, threads)
            self.marks = prefaulted_zeros(2 * threads * self.num_cols, np.uint8, threads)
        return (
            self.acc[:size].reshape(threads, -1),
            self.weights[:size].reshape(threads, -1),
            self.marks[: 2 * threads * self.num_cols].reshape(threads, -1),
        )

    def next_output(self, num_rows: int) -> tuple[np.ndarray, ...]:
        """``(col, val, starts, counts, costs)``: the output buffer pair whose contents are two
        steps old, and its ``(num_rows,)`` int64 row arrays (not zeroed)."""
        self.turn ^= 1
        if self.rows[self.turn].shape[1] < num_rows:
            self.rows[self.turn] = prefaulted_zeros((3, num_rows), np.int64)
        return (*self.outputs[self.turn], *self.rows[self.turn][:, :num_rows])

    def keep_output(self, col: np.ndarray, val: np.ndarray) -> None:
        """Remember a buffer pair that a step had to grow."""
        self.outputs[self.turn] = (col, val)


class WorkspacePool:
    """Idle :class:`Workspace` objects kept between runs, at most ``max_bytes`` in all (``0``
    keeps nothing), so that mesh after mesh (a training loop) reuses the previous buffers."""

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
            found = [w for w in self._idle if (w.dtype, w.index_dtype) == wanted]
            if found:
                self._idle.remove(found[-1])
        workspace = found[-1] if found else Workspace(num_cols, dtype, capacity, index_dtype)
        workspace.start(num_cols, capacity)
        try:
            yield workspace
        finally:
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


def grown(array: np.ndarray, used: int, needed: int) -> np.ndarray:
    """``array`` if it holds ``needed`` entries, else a larger copy of its first ``used``."""
    if needed <= array.shape[0]:
        return array
    larger = prefaulted_zeros(max(needed, int(1.25 * array.shape[0])), array.dtype)
    larger[:used] = array[:used]
    return larger

"""Thread counts of the compiled kernels, scoped to one library call.

numba's thread count (``numba.set_num_threads``) and parallel chunk size are settings of the
calling thread that outlive a call; a library call that changed them would change the threads
of every later parallel numba function the user runs. :func:`kernel_threads` sets them for
the duration of a ``with`` block and restores what it found.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from ._numba import numba

__all__ = ["kernel_threads", "max_threads"]


def max_threads() -> int:
    """The most threads the kernels can use: numba's pool size (``NUMBA_NUM_THREADS``)."""
    return int(numba.config.NUMBA_NUM_THREADS) if numba is not None else 1


@contextmanager
def kernel_threads(count: int, chunk_size: int | None = None) -> Iterator[int]:
    """Run the enclosed kernels on ``count`` threads (capped at :func:`max_threads`), with
    ``prange`` iterations handed out ``chunk_size`` at a time if given; yield the count used.

    Everything is restored on exit, so the caller's numba settings are as they were.
    """
    if numba is None:
        yield 1
        return
    threads = max(1, min(int(count), max_threads()))
    previous = numba.get_num_threads()
    numba.set_num_threads(threads)
    previous_chunk = None if chunk_size is None else numba.set_parallel_chunksize(chunk_size)
    try:
        yield threads
    finally:
        if previous_chunk is not None:
            numba.set_parallel_chunksize(previous_chunk)
        numba.set_num_threads(previous)

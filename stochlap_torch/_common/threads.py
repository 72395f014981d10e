"""Thread counts of one library call: kernels in parallel, torch's glue on the calling thread.

A library call spends most of its time in the compiled kernels, which run on their own
Python threads with dynamic work sharing (a thread descheduled by a busy machine delays no
other). Around them sit many small torch operations (edge lists, Morton codes, sorts, the
saliency map): torch runs each of more than ~32k elements as an OpenMP parallel region whose
barrier waits for its slowest thread. On a loaded machine that thread is often descheduled,
and each such operation costs a scheduler time slice: on a busy machine the glue, not the
kernels, then takes most of a call.

:func:`serial_glue` therefore runs a call's torch operations on the calling thread alone,
while :func:`worker_threads` keeps telling the kernels the count the caller had set
(``torch.get_num_threads()`` on entry). The setting is the calling thread's own (OpenMP
keeps one per thread) and is restored on exit, so no thread setting of the user's process
changes. This holds for ``backend="torch"`` too, whose steps are many small torch operations:
two threads per operation would wait on each other at every one of them.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import torch

__all__ = ["serial_glue", "worker_threads"]

_STATE = threading.local()


def worker_threads() -> int:
    """Threads for the library's kernels: the caller's ``torch.get_num_threads()`` (as it was
    when the outermost :func:`serial_glue` of this thread began)."""
    count = getattr(_STATE, "workers", None)
    return torch.get_num_threads() if count is None else count


@contextmanager
def serial_glue() -> Iterator[None]:
    """Inside: torch ops of this thread run on it alone; :func:`worker_threads` is unchanged.

    Usable as a decorator (``@serial_glue()``) and nestable.
    """
    before = torch.get_num_threads()
    outer = getattr(_STATE, "workers", None)
    if outer is None:
        _STATE.workers = before
    if before != 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        if torch.get_num_threads() != before:
            torch.set_num_threads(before)
        if outer is None:
            _STATE.workers = None

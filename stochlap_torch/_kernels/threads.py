"""numba, imported once, and the thread driver of the kernels (no numba threading layer).

The kernels are compiled with ``nogil=True`` and run on a few Python threads
(:func:`run_workers`) that take row ranges one at a time from a shared counter
(:func:`next_part`), so a thread the OS parks holds up one small range, not a fixed share.
No native thread pool is started, so a process that used the library can ``fork``
(DataLoader workers; GNU OpenMP aborts or hangs in a forked child) and the caller's thread
settings are never touched.
"""

from __future__ import annotations

import threading

from .._common.cpus import available_cpus

try:
    import numba
except ImportError:  # pragma: no cover - numba is a dependency; kept for exotic platforms
    numba = None


def numba_available() -> bool:
    """Whether the compiled kernels can run here (numba importable)."""
    return numba is not None


def kernel_thread_count(requested: int, work_items: int | None = None) -> int:
    """Threads for one kernel call: ``requested``, at most :func:`available_cpus` and at most
    ``work_items`` (one thread per row range at the most), at least 1."""
    threads = min(int(requested), available_cpus())
    if work_items is not None:
        threads = min(threads, int(work_items))
    return max(1, threads)


def run_workers(worker, threads: int, *args) -> None:
    """Call ``worker(thread, *args)`` once on each of ``threads`` threads and wait for all.

    ``thread`` is ``0..threads-1`` (the caller runs ``0``); a worker uses it to pick its
    scratch rows. The first exception of any worker is raised here, after all have stopped.
    """
    errors: list[BaseException] = []

    def work(thread: int) -> None:
        try:
            worker(thread, *args)
        except BaseException as error:  # re-raised in the caller
            errors.append(error)

    helpers = [threading.Thread(target=work, args=(t,), daemon=True) for t in range(1, threads)]
    for helper in helpers:
        helper.start()
    work(0)
    for helper in helpers:
        helper.join()
    if errors:
        raise errors[0]


if numba is not None:
    from numba import types
    from numba.extending import intrinsic

    @intrinsic
    def next_part(typingctx, counter):
        """``counter[0]`` before adding 1 to it, atomically: the next row range for the
        calling worker (numba has no atomics of its own)."""
        if not (isinstance(counter, types.Array) and counter.dtype == types.int64):
            return None

        def codegen(context, builder, signature, args):
            data = context.make_array(signature.args[0])(context, builder, args[0]).data
            one = context.get_constant(types.int64, 1)
            return builder.atomic_rmw("add", data, one, "monotonic")

        return types.int64(counter), codegen

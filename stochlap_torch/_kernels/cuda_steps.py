"""The streamed steps on a GPU (numba's CUDA target), on arrays already on the GPU, in their
dtype. Experimental: checked only under numba's simulator, not yet on a GPU
(``benchmarks/gpu.py``).

A grid of resident blocks takes rows from an atomic counter and carries each from ``F^(1)``
to ``F^(K)``, writing ``D^(k)`` and ``F^(k) P`` straight into the outputs: no ``F^(k)`` is
stored and no grid-wide barrier is needed. Every sum runs in a fixed order, so a run is
reproducible to the bit and differs from the CPU kernel only in the order of its sums (see
:mod:`.cuda_kernel`). Rows that overflow a round's scratch are redone with more, at last with
room for every vertex. The kernels are compiled on the first launch in each process; with
``NUMBA_ENABLE_CUDASIM=1`` (set before numba is imported) they run in numba's simulator on
numpy arrays (the tests).
"""

from __future__ import annotations

import contextlib
import logging
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from .._common.errors import ParameterError
from .block import row_width
from .threads import numba_available

logger = logging.getLogger(__name__)

#: Threads of a block and column-table slots (16 bytes each) it keeps in shared memory (larger
#: tables go to global memory); under the simulator (a Python thread per CUDA thread), few
#: threads and tables small enough that tiny meshes use both kinds.
LAUNCH = {"gpu": (64, 1024), "simulator": (4, 16)}
#: Blocks per multiprocessor that the grid is sized for (blocks take rows from a counter: more
#: than the resident ones just wait their turn).
BLOCKS_PER_SM = 16
#: Upper bound on the scratch of one round (the grid shrinks to fit).
SCRATCH_BYTES = 1 << 30
#: Columns of a row's product that the first round makes room for, at least.
FIRST_ROUND_COLUMNS = 1024

#: ``allocate(shape, dtype)``: a zero-filled array for the kernel (see :func:`kernel_array`).
Allocator = Callable[[tuple[int, ...], np.dtype], Any]


class CudaLhat(NamedTuple):
    """``Lhat = diag(diagonal) + W`` as the CUDA kernel reads it (kernel arrays): ``(V,)``
    float ``diagonal``, ``W`` in CSR form (``int64`` rows, ``int32`` columns), its transpose
    ``t_*`` (each row's columns ascending) and ``(V,)`` ``row_sums`` of ``Lhat``."""

    diagonal: Any
    w_crow: Any
    w_col: Any
    w_val: Any
    t_crow: Any
    t_col: Any
    t_val: Any
    row_sums: Any


def cuda_simulator_enabled() -> bool:
    """Whether numba's CUDA simulator is on (``NUMBA_ENABLE_CUDASIM=1`` before import)."""
    if not numba_available():
        return False
    from numba.core import config

    return bool(config.ENABLE_CUDASIM)


def cuda_available() -> bool:
    """Whether numba's CUDA target can run the kernel on a real GPU here
    (``numba.cuda.is_available()``: a driver and libNVVM; never under the simulator)."""
    if not numba_available() or cuda_simulator_enabled():
        return False
    try:
        from numba import cuda

        return bool(cuda.is_available())
    except Exception:  # a broken CUDA install must not break CPU runs
        return False


def on_device(index: int | None):
    """A context in which numba's launches and allocations go to CUDA device ``index`` (the
    tensors' device: numba otherwise uses its own current device, not torch's); nothing to
    select under the simulator or for ``None``."""
    if index is None or cuda_simulator_enabled():
        return contextlib.nullcontext()
    from numba import cuda

    return cuda.gpus[index]


def kernel_array(array):
    """``array`` as the kernel takes it, without a copy: a numba view of anything with the
    CUDA array interface (a torch CUDA tensor), or, under the simulator only, a numpy view of
    a CPU array (else a :class:`ParameterError`)."""
    if hasattr(array, "__cuda_array_interface__"):
        from numba import cuda

        return cuda.as_cuda_array(array, sync=False)  # the kernel runs on the caller's stream
    if cuda_simulator_enabled():
        return np.asarray(array)
    raise ParameterError("the CUDA kernel takes GPU arrays (CPU arrays under the simulator only)")


def _to_host(array, stream) -> np.ndarray:
    """A host copy of a small kernel array (waits for the stream)."""
    if isinstance(array, np.ndarray):
        return array.copy()
    host = array.copy_to_host(stream=stream)
    if stream != 0:
        stream.synchronize()
    return host


class _Round(NamedTuple):
    """Room per block in one round: product columns, table slots, row entries."""

    columns: int
    slots: int
    width: int


def _rounds(num_vertices: int, max_degree: int, threshold: float, threads: int) -> list[_Round]:
    """The rounds' room: estimated, bounded by the row width, then every vertex."""
    width = row_width(num_vertices, max_degree + 1, threshold)
    plans = [
        (min(num_vertices, max(FIRST_ROUND_COLUMNS, 2 * width)), width),
        (min(num_vertices, width * (max_degree + 1)), width),
        (num_vertices, num_vertices),
    ]
    rounds: list[_Round] = []
    for columns, entries in plans:
        # A row keeps at most its product's columns; F^(1)'s rows (max_degree + 1) fit both.
        entries = min(entries, columns)
        if rounds and columns <= rounds[-1].columns and entries <= rounds[-1].width:
            continue
        slots = 1 << max(1, math.ceil(math.log2(max(2 * columns, 2 * threads))))
        rounds.append(_Round(columns, slots, entries))
    return rounds


def _block_bytes(plan: _Round, value_bytes: int) -> int:
    """Scratch bytes of one block: the table (key, owner, number), candidates, two rows."""
    return plan.slots * 16 + plan.columns * (4 + value_bytes) + 2 * plan.width * (4 + value_bytes)


def _launch() -> tuple[int, int]:
    """``(threads per block, shared table slots)``."""
    return LAUNCH["simulator" if cuda_simulator_enabled() else "gpu"]


def cuda_scratch_floor(
    num_vertices: int, max_degree: int, threshold: float, value_bytes: int
) -> int:
    """Bytes of scratch :func:`stream_steps_cuda` needs at least (one block of its first
    round); it runs as many blocks at once as its ``scratch_bytes`` hold."""
    plan = _rounds(num_vertices, max_degree, float(threshold), _launch()[0])[0]
    return _block_bytes(plan, value_bytes)


def stream_steps_cuda(
    lhat: CudaLhat,
    alpha,
    threshold: float,
    points,
    rows,
    differences,
    positions,
    row_target,
    *,
    max_degree: int,
    allocate: Allocator,
    stream_pointer: int | None = None,
    scratch_bytes: int = SCRATCH_BYTES,
) -> np.ndarray:
    """Steps ``2..K`` of the rows ``rows`` on the GPU, as :func:`~.steps.stream_steps` on the
    CPU; arrays are kernel arrays (:func:`kernel_array`) on one device, in one float dtype.

    Args:
        lhat, alpha, threshold, points: the split ``Lhat`` (``V`` vertices), ``(V,)``
            ``alpha``, ``lambda``, ``(V, C)`` positions ``P``.
        rows: ``(n,)`` int32 rows to compute.
        differences, positions, row_target: outputs as for :func:`~.steps.stream_steps`.
        max_degree: the longest row of ``W``.
        allocate: makes the scratch (zero-filled arrays on the same device).
        stream_pointer: the CUDA stream to launch on (torch's current one); ``None``: numba's
            default stream.
        scratch_bytes: the scratch a round may allocate: the grid shrinks to fit, down to one
            block (:func:`cuda_scratch_floor` for the first round).

    Returns:
        ``(K - 1,)`` int64: the stored entries of ``F^(2..K)`` in these rows.
    """
    from .cuda_kernel import MAX_SCALES, make_stream_kernel

    threads, shared_slots = _launch()
    num_vertices = int(lhat.diagonal.shape[0])
    num_scales = int(differences.shape[0])
    if num_vertices > np.iinfo(np.int32).max:
        raise ParameterError(f"the CUDA kernel indexes columns in int32, not {num_vertices}")
    if not 2 <= num_scales <= MAX_SCALES:
        raise ParameterError(f"the CUDA kernel runs 2 to {MAX_SCALES} scales, not {num_scales}")
    value_dtype = np.dtype(lhat.w_val.dtype)
    kernel = make_stream_kernel(threads, shared_slots)
    int32, int64 = np.dtype(np.int32), np.dtype(np.int64)
    entries = allocate((num_scales,), int64)
    stream = 0
    if cuda_simulator_enabled():  # blocks run in turn: a couple keep it busy
        most_blocks = 2
    else:
        from numba import cuda

        if stream_pointer is not None:
            stream = cuda.external_stream(stream_pointer)
        most_blocks = cuda.get_current_device().MULTIPROCESSOR_COUNT * BLOCKS_PER_SM
        most_blocks = most_blocks * 64 // threads
    pending = rows
    for plan in _rounds(num_vertices, max_degree, float(threshold), threads):
        count = int(pending.shape[0])
        if count == 0:
            break
        fits = scratch_bytes // _block_bytes(plan, value_dtype.itemsize)
        grid = max(1, min(count, most_blocks, fits))
        logger.debug("%d blocks for %d rows in %s", grid, count, plan)
        failed, failed_count = allocate((count,), int32), allocate((1,), int64)
        table = [allocate((grid, plan.slots), dtype) for dtype in (int32, int64, int32)]
        candidates = [allocate((grid, plan.columns), dtype) for dtype in (int32, value_dtype)]
        row_pairs = [allocate((grid, 2, plan.width), dtype) for dtype in (int32, value_dtype)]
        counter = allocate((1,), int64)
        step = (alpha, points, float(threshold), int(max_degree))
        outputs = (differences, positions, entries, failed, failed_count)
        kernel[grid, threads, stream](
            pending, counter, row_target, *lhat, *step, *table, *candidates, *row_pairs, *outputs
        )
        pending = failed[: int(_to_host(failed_count, stream)[0])]
        if int(pending.shape[0]):
            logger.debug("%d rows overflowed %s and are redone", int(pending.shape[0]), plan)
    if int(pending.shape[0]):  # the last round has room for every vertex
        raise RuntimeError(f"{int(pending.shape[0])} rows overflowed the CUDA kernel's scratch")
    return _to_host(entries, stream)[1:]

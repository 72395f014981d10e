"""The streamed run on a GPU: torch tensors in, the CUDA kernel
(:func:`stochlap_torch._kernels.stream_steps_cuda`), torch tensors out.

Every array stays on the tensors' device and in their dtype: ``Lhat`` is split (diagonal,
``W`` and its transpose) with torch ops there, the kernel reads the tensors in place through
the CUDA array interface, and writes ``D^(k)`` and ``F^(k) P`` into tensors allocated there,
on torch's current stream. Under numba's CUDA simulator the same code runs on CPU tensors
(the tests).
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch import Tensor

from .. import _kernels
from .._common.checks import format_bytes
from ..mesh import Renumbering
from ..operators import MeshOperators
from .memory import MEMORY_ENV, MemoryBudgetError
from .parameters import ProgressCallback

__all__ = ["cuda_lhat", "streamed_cuda"]


def _torch_dtype(dtype: np.dtype) -> torch.dtype:
    return torch.from_numpy(np.empty(0, dtype=dtype)).dtype


def cuda_lhat(ops: MeshOperators, dtype: torch.dtype) -> tuple[_kernels.CudaLhat, int]:
    """``Lhat`` split for the CUDA kernel on its device (values in ``dtype``), and the longest
    row of ``W``.

    ``W`` is ``Lhat`` without its diagonal, in CSR form with int32 columns; its transpose is
    ordered by a stable sort of the columns, so each of its rows lists its columns ascending.
    The row sums are summed in row order by a kernel, as the CPU kernel's split does.
    """
    crow, col, val = ops.lhat.crow, ops.lhat.col, ops.lhat.val.to(dtype)
    num_vertices = ops.num_vertices
    device = val.device
    row = torch.repeat_interleave(torch.arange(num_vertices, device=device), crow.diff())
    off = col != row
    diagonal = torch.zeros(num_vertices, dtype=dtype, device=device)
    diagonal.index_add_(0, row[~off], val[~off])  # one diagonal entry per row: exact
    w_counts = torch.bincount(row[off], minlength=num_vertices)
    w_crow = torch.zeros(num_vertices + 1, dtype=torch.int64, device=device)
    torch.cumsum(w_counts, 0, out=w_crow[1:])
    w_col, w_val = col[off].to(torch.int32), val[off].contiguous()
    order = torch.sort(w_col, stable=True).indices
    t_crow = torch.zeros_like(w_crow)
    torch.cumsum(torch.bincount(w_col, minlength=num_vertices), 0, out=t_crow[1:])
    t_col, t_val = row[off][order].to(torch.int32), w_val[order]
    row_sums = torch.empty(num_vertices, dtype=dtype, device=device)
    # The kernel arrays view the tensors and hold them (no copy).
    arrays = _kernels.CudaLhat(
        *map(
            _kernels.kernel_array, (diagonal, w_crow, w_col, w_val, t_crow, t_col, t_val, row_sums)
        )
    )
    _kernels.lhat_row_sums(
        _kernels.kernel_array(crow.contiguous()),
        _kernels.kernel_array(val.contiguous()),
        arrays.row_sums,
        _stream_pointer(device),
    )
    max_degree = int(w_counts.max()) if num_vertices else 0
    return arrays, max_degree


def _stream_pointer(device: torch.device) -> int | None:
    """torch's current CUDA stream on ``device`` (``None`` on the CPU)."""
    return torch.cuda.current_stream(device).cuda_stream if device.type == "cuda" else None


def streamed_cuda(
    ops: MeshOperators,
    points: Tensor,
    num_scales: int,
    threshold: float,
    rows: tuple[int, int],
    progress: ProgressCallback | None,
    renumbering: Renumbering | None,
    scratch: int = _kernels.SCRATCH_BYTES,
) -> tuple[Tensor, Tensor, list[int]]:
    """Steps ``2..K`` of the rows ``[start, stop)`` with the CUDA kernel, whose scratch takes
    at most ``scratch`` bytes (:class:`~.memory.MemoryBudgetError` if one block needs more).

    Returns ``(positions, differences, entries)``: ``(K, R, C)`` and ``(K, R)`` on the
    points' device (in the original vertex order when ``renumbering`` is given) and the
    entries of ``F^(2..K)``. With a ``progress`` callback the rows go to the kernel in
    ``K - 1`` slices, ``progress(k, K)`` after the ``(k - 1)``-th.
    """
    # Launches, streams and scratch on the tensors' GPU, whichever device is current.
    device = points.device
    index = device.index if device.type == "cuda" else None
    select = torch.cuda.device(device) if index is not None else contextlib.nullcontext()
    with select, _kernels.on_device(index):
        return _streamed(ops, points, num_scales, threshold, rows, progress, renumbering, scratch)


def _streamed(
    ops: MeshOperators,
    points: Tensor,
    num_scales: int,
    threshold: float,
    rows: tuple[int, int],
    progress: ProgressCallback | None,
    renumbering: Renumbering | None,
    scratch: int,
) -> tuple[Tensor, Tensor, list[int]]:
    """:func:`streamed_cuda` on the current device."""
    start, stop = rows
    count = stop - start
    device, dtype = points.device, points.dtype
    lhat, max_degree = cuda_lhat(ops, dtype)
    floor = _kernels.cuda_scratch_floor(
        ops.num_vertices, max_degree, threshold, points.element_size()
    )
    if scratch < floor:
        raise MemoryBudgetError(
            f"the CUDA kernel needs {format_bytes(floor)} of scratch for a block of rows, "
            f"over the {format_bytes(max(scratch, 0))} the budget leaves after the outputs. "
            f"Raise the budget (max_memory=..., or ${MEMORY_ENV})."
        )
    alpha = ops.alpha.to(dtype).contiguous()
    points = points.contiguous()
    positions = torch.zeros((num_scales, count, points.shape[1]), dtype=dtype, device=device)
    differences = torch.zeros((num_scales, count), dtype=dtype, device=device)
    if renumbering is None:
        target = torch.arange(ops.num_vertices, device=device) - start
        positions[0] = points[start:stop]
    else:
        target = renumbering.order.to(device)
        positions[0].index_copy_(0, target, points)
    pointer = _stream_pointer(device)

    def allocate(shape, numpy_dtype):  # scratch from torch's allocator, on its device
        return _kernels.kernel_array(
            torch.zeros(shape, dtype=_torch_dtype(numpy_dtype), device=device)
        )

    slices = num_scales - 1 if progress is not None else 1
    bounds = np.linspace(start, stop, slices + 1).round().astype(np.int64)
    entries = np.zeros(num_scales - 1, dtype=np.int64)
    arrays = [_kernels.kernel_array(t) for t in (alpha, points, differences, positions, target)]
    for piece in range(slices):
        low, high = int(bounds[piece]), int(bounds[piece + 1])
        if high > low:
            piece_rows = torch.arange(low, high, dtype=torch.int32, device=device)
            entries += _kernels.stream_steps_cuda(
                lhat,
                arrays[0],
                threshold,
                arrays[1],
                _kernels.kernel_array(piece_rows),
                arrays[2],
                arrays[3],
                arrays[4],
                max_degree=max_degree,
                allocate=allocate,
                stream_pointer=pointer,
                scratch_bytes=scratch,
            )
        if progress is not None:
            progress(piece + 2, num_scales)
    return positions, differences, entries.tolist()

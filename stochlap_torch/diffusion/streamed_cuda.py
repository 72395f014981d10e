"""The streamed run on a GPU by the CUDA kernel
(:func:`stochlap_torch._kernels.stream_steps_cuda`). Experimental: not yet checked on a GPU
(``benchmarks/gpu.py``).

Every array stays on the tensors' device and in their dtype; the kernel reads the tensors in
place through the CUDA array interface, on torch's current stream. Under numba's CUDA
simulator the same code runs on CPU tensors (the tests).
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch
from torch import Tensor

from .. import _kernels
from .._common.checks import format_bytes
from ..operators import MeshOperators
from .memory import MEMORY_ENV, MemoryBudgetError

__all__ = ["cuda_device", "cuda_lhat", "cuda_rows"]


def cuda_lhat(ops: MeshOperators, dtype: torch.dtype) -> tuple[_kernels.CudaLhat, int]:
    """``Lhat`` split for the CUDA kernel on its device (values in ``dtype``), and the longest
    row of ``W`` (``Lhat`` without its diagonal, int32 columns). A stable sort of the columns
    orders the transpose, so each of its rows lists its columns ascending; the row sums are
    summed in row order by a kernel, as the CPU kernel's split does.
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
    tensors = (diagonal, w_crow, w_col, w_val, t_crow, t_col, t_val, row_sums)
    arrays = _kernels.CudaLhat(*map(_kernels.kernel_array, tensors))
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


@contextlib.contextmanager
def cuda_device(device: torch.device):
    """Launches, streams and scratch on ``device`` (the tensors' GPU), whichever is current."""
    index = device.index if device.type == "cuda" else None
    select = torch.cuda.device(device) if index is not None else contextlib.nullcontext()
    with select, _kernels.on_device(index):
        yield


def cuda_rows(ops: MeshOperators, points: Tensor, threshold: float, scratch: int):
    """``run(rows, positions, differences, target)`` for the engine's streamed driver: steps
    ``2..K`` of the rows ``[low, high)`` by the CUDA kernel, whose scratch takes at most
    ``scratch`` bytes; returns their entries of ``F^(2..K)``.

    Raises:
        MemoryBudgetError: one block of rows needs more scratch than ``scratch``.
    """
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
    alpha = _kernels.kernel_array(ops.alpha.to(dtype).contiguous())
    moved = _kernels.kernel_array(points.contiguous())
    pointer = _stream_pointer(device)

    def allocate(shape, numpy_dtype):  # scratch from torch's allocator, on its device
        torch_dtype = torch.from_numpy(np.empty(0, dtype=numpy_dtype)).dtype
        return _kernels.kernel_array(torch.zeros(shape, dtype=torch_dtype, device=device))

    def run(rows, positions, differences, target):
        piece = torch.arange(*rows, dtype=torch.int32, device=device)
        arrays = map(_kernels.kernel_array, (piece, differences, positions, target))
        return _kernels.stream_steps_cuda(
            lhat,
            alpha,
            threshold,
            moved,
            *arrays,
            max_degree=max_degree,
            allocate=allocate,
            stream_pointer=pointer,
            scratch_bytes=scratch,
        )

    return run

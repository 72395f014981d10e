"""The engine: :func:`run_steps`, the only place that runs Algorithm 1, with the memory check
and the progress reports. A run on the numba or CUDA backend that keeps no operator and tracks
no gradient is streamed (each row through every step, no ``F^(k)`` stored); every other run
steps whole operators with :func:`~.step.scale_steps`.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from .. import _kernels
from .._common.checks import format_bytes
from .._common.errors import ParameterError
from ..mesh import Renumbering
from ..operators import MeshOperators
from ..sparse import CSR, permute_csr, slice_rows
from ..sparse.csr import row_ids
from .memory import MEMORY_ENV, MemoryBudgetError, check_memory, check_streamed_memory
from .parameters import ProgressCallback, resolve_backend
from .representation import MultiscaleRepresentation
from .step import ConstantOperatorStep, kernel_lhat, scale_steps

logger = logging.getLogger(__name__)

#: ``step(F^(k-1)) -> (F^(k), D^(k), F^(k) P)``.
StepFunction = Callable[[CSR], tuple[CSR, Tensor, Tensor]]


@dataclass
class Steps:
    """What :func:`run_steps` produced on its ``R`` rows, scales ``k = 1..K``: ``(K, R, C)``
    ``positions`` (the input, then ``F^(k) P``), ``(K, R)`` ``differences`` (``D^(k)``, zero
    at ``k = 1``), the ``K`` stored ``entries`` of ``F^(1..K)`` and, when kept, the
    ``operators`` ``F^(1..K)`` as :class:`~stochlap_torch.sparse.CSR` (else ``None``)."""

    positions: Tensor
    differences: Tensor
    entries: list[int]
    operators: list[CSR] | None

    def representation(self, scale: float, batch: Tensor | None) -> MultiscaleRepresentation:
        """These steps of a mesh whose positions were multiplied by ``scale``, in its units (the
        operators, if kept, detached)."""
        operators = self.operators
        if operators is not None:
            operators = [op.with_values(op.val.detach()).to_sparse_csr() for op in operators]
        return MultiscaleRepresentation(
            positions=self.positions if scale == 1.0 else self.positions / scale,
            differences=self.differences,
            entries=torch.tensor(self.entries, dtype=torch.int64),
            operators=operators,
            batch=batch,
        )


def run_steps(
    ops: MeshOperators,
    points: Tensor,
    num_scales: int,
    threshold: float,
    *,
    backend: str = "auto",
    rows: tuple[int, int] | None = None,
    keep_operators: bool = False,
    step: StepFunction | None = None,
    first: CSR | None = None,
    progress: ProgressCallback | None = None,
    max_memory: int | None = None,
    renumbering: Renumbering | None = None,
) -> Steps:
    """Algorithm 1 from ``F^(1)`` (``Lhat`` normalised by rows) to ``F^(K)``.

    Args:
        ops: the operators, in the vertex order of ``points``.
        points: ``(V, C)`` float positions ``P`` (any number of channels); gradients reach
            them through ``F^(k) P``.
        num_scales: ``K >= 2`` (checked by the caller).
        threshold: ``lambda`` in ``(0, 1)``.
        backend: one of :data:`~.parameters.BACKENDS` (``"cuda"`` is experimental).
        rows: ``(start, stop)``, the ``R`` rows of every ``F^(k)`` this run computes (default:
            all); a streamed numba range starts at a multiple of ``_kernels.LANES``.
        keep_operators: return every ``F^(k)``.
        step: the step function (default: :class:`~.step.ConstantOperatorStep`); a custom
            step also needs ``first``, and always steps whole operators.
        first: ``F^(1)`` on the run's rows (default: from ``ops``).
        progress: ``progress(k, K)`` as the run advances (streamed: after each ``(K - 1)``-th
            of the rows; ``None``: no reports).
        max_memory: byte budget (default: :func:`~.memory.default_memory_budget`).
        renumbering: that of ``ops`` and ``points``, if renumbered (``None``: not): the
            results (and operators) come in the original vertex order (all rows only).

    Raises:
        MemoryBudgetError: the run would exceed the budget.
    """
    asked, backend = backend, resolve_backend(backend, points.device)
    start, stop = (0, ops.num_vertices) if rows is None else rows
    if renumbering is not None and (start, stop) != (0, ops.num_vertices):
        raise ParameterError("a renumbered run must compute every row")
    whole = keep_operators or step is not None or points.requires_grad
    streamed = backend in ("numba", "cuda") and not whole
    if backend == "cuda" and not streamed:
        if asked == "cuda":  # insisted on: never a silent fallback
            raise ParameterError(
                "backend='cuda' streams rows through the scales and keeps no operator nor "
                "gradient graph: with return_operators, a differentiable step or vertices that "
                "require grad, use backend='auto' or 'torch'"
            )
        backend = "torch"  # "auto": whole operators and gradients take the torch ops
    if streamed:
        scratch = check_streamed_memory(ops, num_scales, max_memory, backend)
    else:
        # A custom step is the differentiable one: its graph holds every step.
        budget = (max_memory, backend, step is not None)
        check_memory(ops, num_scales, threshold, keep_operators, *budget)
    if progress is not None:
        progress(1, num_scales)
    if streamed:
        points = points.detach()
        kernel = _cuda_rows if backend == "cuda" else _numba_rows
        with kernel(ops, points, threshold, scratch) as (run, align):
            rows = (start, stop)
            return _streamed(ops, points, num_scales, rows, progress, renumbering, run, align)
    if step is None:
        step = ConstantOperatorStep(ops, threshold, points, backend, sort_columns=keep_operators)
    if first is None:
        first = slice_rows(ops.stochastic_laplacian(), start, stop)
    result = _stepped(first, step, points[start:stop], num_scales, keep_operators, progress)
    if renumbering is not None:
        result.positions = renumbering.restore(result.positions, dim=1)
        result.differences = renumbering.restore(result.differences, dim=1)
        if result.operators is not None:
            result.operators = [permute_csr(op, renumbering.order) for op in result.operators]
    return result


def _stepped(
    first: CSR,
    step: StepFunction,
    points: Tensor,
    num_scales: int,
    keep_operators: bool,
    progress: ProgressCallback | None,
) -> Steps:
    """Whole operators, one step at a time (:func:`~.step.scale_steps`)."""
    positions, differences = [points], [points.new_zeros(first.num_rows)]
    entries = [first.nnz]
    operators = [first] if keep_operators else None
    for k, following, difference, moved in scale_steps(first, step, num_scales):
        differences.append(difference)
        positions.append(moved)
        entries.append(following.nnz)
        if operators is not None:
            operators.append(following)
        per_row = following.nnz / max(first.num_rows, 1)
        logger.debug("scale %d/%d: %.1f entries per row", k, num_scales, per_row)
        if progress is not None:
            progress(k, num_scales)
    return Steps(torch.stack(positions), torch.stack(differences), entries, operators)


def _prefaulted_zeros(shape: tuple[int, ...], dtype: torch.dtype, device) -> Tensor:
    """``torch.zeros``, on the CPU with its pages touched (``_kernels.prefaulted_zeros``)."""
    if device.type != "cpu":
        return torch.zeros(shape, dtype=dtype, device=device)
    numpy_dtype = torch.empty(0, dtype=dtype).numpy().dtype
    return torch.from_numpy(_kernels.prefaulted_zeros(shape, numpy_dtype, torch.get_num_threads()))


@contextlib.contextmanager
def _numba_rows(ops: MeshOperators, points: Tensor, threshold: float, scratch: int):
    """``(run, align)`` for :func:`_streamed` by the numba kernel (scratch rows from the
    workspace pool; ``scratch`` is the CUDA kernel's), in blocks of ``LANES`` rows."""
    lhat, alpha = kernel_lhat(ops)  # the kernel takes F^(1) from Lhat, row by row
    moved = points.numpy().astype(alpha.dtype, copy=False)
    index = lhat.w_col.dtype
    with _kernels.WORKSPACES.borrow(ops.num_vertices, alpha.dtype, 0, index) as space:

        def run(rows, positions, differences, target):
            arrays = (differences.numpy(), positions.numpy(), target.numpy(), space)
            threads = torch.get_num_threads()
            return _kernels.stream_steps(lhat, alpha, threshold, moved, threads, rows, *arrays)

        yield run, _kernels.LANES


def _cuda_lhat(ops: MeshOperators, dtype: torch.dtype) -> tuple[_kernels.CudaLhat, int]:
    """``Lhat`` split for the CUDA kernel on its device (int32 columns, values in ``dtype``,
    with the transpose of ``W``, columns ascending), and the longest row of ``W``."""
    lhat = (ops.lhat.crow, ops.lhat.col, ops.lhat.val.to(dtype))
    split = _kernels.split_lhat(*(t.cpu().numpy() for t in lhat), np.int32)
    device = ops.lhat.val.device
    diagonal, w_crow, w_col, w_val, row_sums = (torch.from_numpy(a).to(device) for a in split)
    order = torch.sort(w_col, stable=True).indices
    t_crow = torch.zeros_like(w_crow)
    torch.cumsum(torch.bincount(w_col, minlength=ops.num_vertices), 0, out=t_crow[1:])
    t_col, t_val = row_ids(w_crow)[order].to(torch.int32), w_val[order]
    # The kernel arrays view the tensors and hold them (no copy).
    tensors = (diagonal, w_crow, w_col, w_val, t_crow, t_col, t_val, row_sums)
    max_degree = int(w_crow.diff().max()) if ops.num_vertices else 0
    return _kernels.CudaLhat(*map(_kernels.kernel_array, tensors)), max_degree


@contextlib.contextmanager
def _cuda_rows(ops: MeshOperators, points: Tensor, threshold: float, scratch: int):
    """``(run, 1)`` for :func:`_streamed` by the CUDA kernel (experimental) on the tensors'
    device, in place (CPU ones under numba's simulator), with at most ``scratch`` bytes of
    scratch: :class:`MemoryBudgetError` if a block of rows needs more."""
    device, dtype = points.device, points.dtype
    index = device.index if device.type == "cuda" else None
    select = torch.cuda.device(device) if index is not None else contextlib.nullcontext()
    with select, _kernels.on_device(index):
        lhat, max_degree = _cuda_lhat(ops, dtype)
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
        stream = torch.cuda.current_stream(device).cuda_stream if device.type == "cuda" else None

        def allocate(shape, numpy_dtype):  # scratch from torch's allocator, on its device
            torch_dtype = torch.from_numpy(np.empty(0, dtype=numpy_dtype)).dtype
            return _kernels.kernel_array(torch.zeros(shape, dtype=torch_dtype, device=device))

        options = {"max_degree": max_degree, "allocate": allocate, "stream_pointer": stream}

        def run(rows, positions, differences, target):
            piece = torch.arange(*rows, dtype=torch.int32, device=device)
            arrays = map(_kernels.kernel_array, (piece, differences, positions, target))
            return _kernels.stream_steps_cuda(
                lhat, alpha, threshold, moved, *arrays, **options, scratch_bytes=scratch
            )

        yield run, 1


def _streamed(
    ops: MeshOperators,
    points: Tensor,
    num_scales: int,
    rows: tuple[int, int],
    progress: ProgressCallback | None,
    renumbering: Renumbering | None,
    run: Callable[[tuple[int, int], Tensor, Tensor, Tensor], np.ndarray],
    align: int,
) -> Steps:
    """Steps ``2..K``, the rows through every step at once: ``run(rows, positions,
    differences, target)`` computes the rows ``[low, high)`` into rows ``target[i]`` of the
    outputs and returns their entries of ``F^(2..K)``; in ``K - 1`` slices of whole blocks of
    ``align`` rows with a ``progress`` callback, else in one call."""
    start, stop = rows
    count = stop - start
    device = points.device
    positions = _prefaulted_zeros((num_scales, count, points.shape[1]), points.dtype, device)
    differences = _prefaulted_zeros((num_scales, count), points.dtype, device)
    if renumbering is None:
        target = torch.arange(ops.num_vertices, device=device) - start
        positions[0] = points[start:stop]
    else:
        target = renumbering.order.to(device)
        positions[0].index_copy_(0, target, points)
    slices = num_scales - 1 if progress is not None else 1
    blocks = -(-count // align)
    steps = np.linspace(0, blocks, slices + 1).round().astype(np.int64)
    bounds = np.minimum(start + steps * align, stop)
    entries = np.zeros(num_scales - 1, dtype=np.int64)
    for piece in range(slices):
        low, high = int(bounds[piece]), int(bounds[piece + 1])
        if high > low:
            entries += run((low, high), positions, differences, target)
        if progress is not None:
            progress(piece + 2, num_scales)
    for k, total in enumerate(entries.tolist(), start=2):
        logger.debug("scale %d/%d: %.1f entries per row", k, num_scales, total / max(count, 1))
    first_entries = int(ops.lhat.crow[stop] - ops.lhat.crow[start])
    return Steps(positions, differences, [first_entries, *entries.tolist()], None)

"""The memory a run will need, estimated before it starts, and the budget it must fit: rows
of ``F^(k)`` evolve independently, so a few hundred evenly spread rows, stepped like the run,
predict the fill at every scale. A streamed run's is known in advance (:func:`streamed_memory`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch

from .. import _kernels
from .._common.checks import check_int, check_number, format_bytes
from .._common.errors import ParameterError, StochlapError
from ..operators import MeshOperators
from ..sparse import select_rows
from .parameters import check_parameters, resolve_backend
from .step import ConstantOperatorStep, scale_steps

#: Bytes of the int64 column index of one stored entry of ``F``.
_INDEX_BYTES = 8
#: Environment variable that overrides the default memory budget, in bytes.
MEMORY_ENV = "STOCHLAP_MAX_MEMORY"
#: Rows sampled by :func:`estimate_memory`.
SAMPLE_ROWS = 256
#: Safety factor on the sampled fill, for the spread between rows.
_SAMPLE_MARGIN = 1.25
#: The output of a step is allocated with room to spare before it is filled.
_OUTPUT_SLACK = 1.5


class MemoryBudgetError(StochlapError, MemoryError):
    """The run would exceed the memory budget (usually: threshold too close to 0)."""


def _checked_budget(name: str, value) -> int:
    """``value`` as a whole number of bytes above zero (:class:`ParameterError` naming ``name``)."""
    return int(check_number(name, value, 0.0, None, open_low=True))


def default_memory_budget() -> int:
    """Bytes the operators may use: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory.

    Raises:
        ParameterError: ``$STOCHLAP_MAX_MEMORY`` is not a finite number of bytes above zero.
    """
    if MEMORY_ENV in os.environ:
        text = os.environ[MEMORY_ENV]
        try:
            value = float(text)
        except ValueError:
            raise ParameterError(f"${MEMORY_ENV} must be a number of bytes, got {text!r}") from None
        return _checked_budget(f"${MEMORY_ENV}", value)
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30


@dataclass(frozen=True)
class MemoryEstimate:
    """What the operators of a run will cost: ``peak_bytes`` held at once, the ``(K,)`` mean
    stored ``entries_per_row`` of ``F^(1..K)``, and ``complete``, ``False`` if sampling stopped
    early over the budget (then fewer than ``K`` entries)."""

    peak_bytes: int
    entries_per_row: list[float]
    complete: bool


def _scratch_bytes(num_vertices: int, value_bytes: int) -> int:
    """The numba kernel's scratch: two ``(V, LANES)`` float and two byte rows per thread."""
    per_thread = num_vertices * (2 * _kernels.LANES * value_bytes + 2)
    return torch.get_num_threads() * per_thread


def estimate_memory(
    ops: MeshOperators,
    num_scales: int,
    threshold: float,
    return_operators: bool = False,
    budget: int | None = None,
    sample_rows: int = SAMPLE_ROWS,
    backend: str = "auto",
    differentiable: bool = False,
) -> MemoryEstimate:
    """Estimate the memory of the operators by running the steps on a sample of rows; the
    peak also counts the positions and coefficients a run returns and the kernel's scratch.

    Args:
        ops: the mesh operators.
        num_scales: ``K``.
        threshold: ``lambda``.
        return_operators: all ``K`` operators are kept (else two at a time).
        budget: stop sampling as soon as the estimate exceeds this many bytes (``None``:
            never, every scale is sampled).
        sample_rows: rows to sample (all rows if the mesh has fewer).
        backend: one of :data:`~.parameters.BACKENDS` (``"torch"`` compiles nothing).
        differentiable: the run keeps an autograd graph through every step (:mod:`.autodiff`).

    Raises:
        ParameterError: ``ops`` not operators, options out of range (as
            :class:`~stochlap_torch.params.PaperParams`), ``sample_rows`` below 1.
    """
    if not isinstance(ops, MeshOperators):
        raise ParameterError(
            f"ops must be MeshOperators (stochlap_torch.mesh_operators), got {type(ops).__name__}"
        )
    num_scales, threshold = check_parameters(num_scales, threshold)
    sample_rows = check_int("sample_rows", sample_rows, minimum=1)
    budget = None if budget is None else _checked_budget("budget", budget)
    num_vertices = ops.num_vertices
    count = min(sample_rows, num_vertices)
    rows = torch.linspace(0, num_vertices - 1, count, device=ops.alpha.device).round().long()
    first = select_rows(ops.stochastic_laplacian(), rows)
    per_row = [first.nnz / count]
    value_bytes = ops.alpha.element_size()
    entry_bytes = _INDEX_BYTES + value_bytes
    # Positions as computed, stacked, and the coefficients: three (K, V, 3) tensors.
    outputs = 3 * num_scales * num_vertices * 3 * value_bytes
    backend = resolve_backend(backend, ops.alpha.device)
    if backend == "numba":
        outputs += _scratch_bytes(num_vertices, value_bytes)
    # Only the fill is wanted: no positions to move.
    step = ConstantOperatorStep(
        ops, threshold, ops.alpha.new_zeros(num_vertices, 0), backend, sort_columns=False
    )
    lhat_lengths = ops.lhat.crow.diff()
    patterns = 0.0  # bytes of the product patterns an autograd graph holds, per row
    peak = 0.0
    previous = first
    for _, sample, _, _ in scale_steps(first, step, num_scales):
        per_row.append(sample.nnz / count)
        if differentiable:  # the product's terms bound its pattern: one per pair of entries
            products = int(lhat_lengths[previous.col].sum()) / count
            # Per term: the pattern's column and sort key, its values, normalised values and
            # their gradients, and the gather indices.
            patterns += products * (2 * _INDEX_BYTES + 5 * value_bytes)
        previous = sample
        keep_all = return_operators or differentiable
        held = sum(per_row) if keep_all else per_row[-2] + _OUTPUT_SLACK * per_row[-1]
        held_bytes = held * entry_bytes + patterns
        peak = max(peak, _SAMPLE_MARGIN * held_bytes * num_vertices + outputs)
        if budget is not None and peak > budget:
            return MemoryEstimate(int(peak), per_row, complete=False)
    return MemoryEstimate(int(peak), per_row, complete=True)


def resolve_budget(max_memory) -> int:
    """The byte budget of a run: ``max_memory``, or :func:`default_memory_budget` if ``None``;
    :class:`ParameterError` unless a finite number above zero."""
    if max_memory is None:
        return default_memory_budget()
    return _checked_budget("max_memory", max_memory)


def check_memory(
    ops: MeshOperators,
    num_scales: int,
    threshold: float,
    return_operators: bool,
    max_memory: int | None,
    backend: str = "auto",
    differentiable: bool = False,
) -> MemoryEstimate:
    """Raise :class:`MemoryBudgetError` if the run would exceed the budget; else the estimate
    (arguments of :func:`estimate_memory`)."""
    budget = resolve_budget(max_memory)
    options = {"budget": budget, "backend": backend, "differentiable": differentiable}
    estimate = estimate_memory(ops, num_scales, threshold, return_operators, **options)
    if estimate.peak_bytes > budget:
        reached = len(estimate.entries_per_row)
        raise MemoryBudgetError(
            f"the operators for {ops.num_vertices} vertices at num_scales={num_scales}, "
            f"threshold={threshold:g} would need more than {format_bytes(estimate.peak_bytes)} "
            f"(about {estimate.entries_per_row[-1]:.0f} entries per row by scale {reached}), "
            f"over the budget of {format_bytes(budget)}. Raise the threshold, lower "
            f"num_scales, or raise the budget (max_memory=..., or ${MEMORY_ENV})."
        )
    return estimate


def streamed_memory(ops: MeshOperators, num_scales: int, backend: str = "numba") -> int:
    """Bytes a streamed run adds to its operators: the ``(K, V, 3)`` positions, the ``(K, V)``
    differences, the ``(K, V, 3)`` coefficients they give on first access, ``Lhat`` split for
    the kernel and, on the numba ``backend``, the kernel's scratch rows."""
    value_bytes = ops.alpha.element_size()
    num_vertices = ops.num_vertices
    outputs = num_scales * num_vertices * (3 + 1 + 3) * value_bytes
    index_bytes = np.dtype(_kernels.index_dtype(num_vertices)).itemsize
    off_diagonal = ops.lhat.nnz - num_vertices
    split = off_diagonal * (index_bytes + value_bytes) + num_vertices * (8 + 2 * value_bytes)
    scratch = 0 if backend == "cuda" else _scratch_bytes(num_vertices, value_bytes)
    return outputs + split + scratch


def check_streamed_memory(
    ops: MeshOperators, num_scales: int, max_memory: int | None, backend: str = "numba"
) -> int:
    """The bytes the budget leaves after :func:`streamed_memory`, at most
    ``_kernels.SCRATCH_BYTES`` (the CUDA kernel's scratch); :class:`MemoryBudgetError` if the
    run would exceed the budget."""
    budget = resolve_budget(max_memory)
    needed = streamed_memory(ops, num_scales, backend)
    if needed > budget:
        raise MemoryBudgetError(
            f"a run on {ops.num_vertices} vertices at num_scales={num_scales} needs "
            f"{format_bytes(needed)} for its outputs and scratch rows, over the budget of "
            f"{format_bytes(budget)}. Lower num_scales, or raise the budget "
            f"(max_memory=..., or ${MEMORY_ENV})."
        )
    return min(budget - needed, _kernels.SCRATCH_BYTES)

"""The diffusion steps of Algorithm 1: ``F^(k)`` from ``F^(k-1)``, and what they produce.

One step, for ``k = 2..K``::

    G     = [F^(k-1) Lhat]_r          (product, row normalisation)
    G     = G with entries < lambda set to 0
    F^(k) = [alpha ∘ G]_r             (Schur product with alpha on every row)

and ``P^(k) = F^(k) P``, ``C^(k) = P^(k-1) - P^(k)``, ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)``
(Algorithm 2). Only ``F^(k-1)`` and ``F^(k)`` are held at once unless the operators are asked
for.
"""

from __future__ import annotations

import logging
import os
import weakref
from collections.abc import Callable, Iterator
from contextlib import closing
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from . import kernel_buffers, kernels
from .batch import check_batch
from .mesh import MeshError, as_mesh_tensors, validate_mesh
from .op_registry import define_op
from .operators import (
    LOCALITY_MIN_VERTICES,
    MeshOperators,
    locality_order,
    operators_of_valid_mesh,
)
from .sparse_ops import (
    CSR,
    csr_matmul,
    dynamic_csr_like,
    normalize_rows,
    permute_csr,
    row_abs_diff_sum,
    scale_columns,
    select_rows,
    spmm,
    threshold_rows,
)

__all__ = [
    "BACKENDS",
    "MemoryBudgetError",
    "MemoryEstimate",
    "MultiscaleRepresentation",
    "check_memory",
    "check_parameters",
    "diffusion_step",
    "estimate_memory",
    "multiscale_representation",
]

logger = logging.getLogger(__name__)

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

ProgressCallback = Callable[[int, int], None]

#: ``"auto"``: the fused numba kernel on CPU when numba is installed, torch ops elsewhere;
#: ``"torch"``: the torch ops on every device (the cross-check); ``"numba"``: insist on it.
BACKENDS = ("auto", "torch", "numba")


class MemoryBudgetError(MemoryError):
    """The operators would exceed the memory budget (usually: threshold too close to 0)."""


@dataclass
class MultiscaleRepresentation:
    """The multiscale representation of one mesh (Algorithm 1), scales ``k = 1..K``.

    Attributes:
        positions: ``(K, V, 3)``; ``positions[0]`` is the input ``P``, ``positions[k-1]`` is
            ``P^(k) = F^(k) P``.
        coefficients: ``(K, V, 3)``; ``coefficients[0] = 0``,
            ``coefficients[k-1] = positions[k-2] - positions[k-1]`` (``C^(k)``). Computed
            from ``positions`` on first access and kept (:func:`scale_coefficients`), so a
            run that needs only saliency or positions never holds them.
        differences: ``(K, V)``; ``differences[0] = 0``, ``differences[k-1]`` is the difference
            map ``D^(k)(i) = sum_j |F^(k)(i, j) - F^(k-1)(i, j)|`` of Algorithm 2.
        entries: ``(K,)`` int64 number of stored entries of each ``F^(k)`` (divide by ``V`` for
            entries per row: the cost of the next step).
        operators: the ``K`` matrices ``F^(1..K)`` as ``(V, V)`` ``torch.sparse_csr`` tensors
            (``F^(1)`` is the stochastic mesh Laplacian; block diagonal for a batch), or
            ``None`` when not requested.
        batch: the ``(V,)`` mesh index of every vertex for a packed batch, else ``None``.
    """

    positions: Tensor
    differences: Tensor
    entries: Tensor
    operators: list[Tensor] | None = None
    batch: Tensor | None = None

    @property
    def num_scales(self) -> int:
        return int(self.positions.shape[0])

    @cached_property
    def coefficients(self) -> Tensor:
        """``(K, V, 3)`` ``C^(k)`` (see the class docstring), computed once: with a graph to
        ``positions`` when they carry gradients and grad mode is on at that first access."""
        return scale_coefficients(self.positions)

    def reconstruct(self) -> Tensor:
        """``(V, 3)`` input positions from the coarsest scale and all coefficients (Eq. 22)."""
        return self.positions[-1] + self.coefficients.sum(dim=0)

    def saliency(self) -> Tensor:
        """``(V,)`` saliency of Algorithm 2, ``log(sum_k D^(k))``."""
        from .saliency_map import saliency_from_differences  # it builds on this module

        return saliency_from_differences(self.differences, self.batch)


def scale_coefficients(positions: Tensor) -> Tensor:
    """``(K, V, C)`` coefficients ``C^(k) = P^(k-1) - P^(k)`` of ``(K, V, C)`` positions
    (Eq. 16), ``C^(1) = 0``; differentiable when ``positions`` carries gradients."""
    if positions.requires_grad and torch.is_grad_enabled():
        return torch.cat([torch.zeros_like(positions[:1]), positions[:-1] - positions[1:]])
    out = torch.empty_like(positions)  # one pass, no temporary
    out[0] = 0
    torch.sub(positions[:-1], positions[1:], out=out[1:])
    return out


def check_parameters(num_scales: int, threshold: float) -> None:
    """Raise ``ValueError`` unless ``num_scales >= 2`` and ``0 < threshold < 1``."""
    if isinstance(num_scales, bool) or not isinstance(num_scales, int) or num_scales < 2:
        raise ValueError(f"num_scales must be an integer >= 2, got {num_scales!r}")
    if not (isinstance(threshold, (int, float)) and 0.0 < threshold < 1.0):
        raise ValueError(f"threshold must lie in the open interval (0, 1), got {threshold!r}")


def default_memory_budget() -> int:
    """Bytes the operators may use: ``$STOCHLAP_MAX_MEMORY``, else half the physical memory."""
    if MEMORY_ENV in os.environ:
        return int(float(os.environ[MEMORY_ENV]))
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") // 2
    except (ValueError, OSError, AttributeError):
        return 8 << 30


@dataclass(frozen=True)
class MemoryEstimate:
    """What the operators of a run will cost, estimated before the run.

    Attributes:
        peak_bytes: estimated peak bytes of the operators held at once.
        entries_per_row: ``(K,)`` estimated mean stored entries per row of ``F^(1..K)``
            (exact for ``F^(1)``).
        complete: ``False`` if sampling stopped early because the budget was already exceeded
            (``entries_per_row`` then covers fewer than ``K`` scales).
    """

    peak_bytes: int
    entries_per_row: list[float]
    complete: bool


def estimate_memory(
    ops: MeshOperators,
    num_scales: int,
    threshold: float,
    return_operators: bool = False,
    budget: int | None = None,
    sample_rows: int = SAMPLE_ROWS,
    backend: str = "auto",
) -> MemoryEstimate:
    """Estimate the memory of the operators by running the steps on a sample of rows.

    Rows of ``F^(k)`` evolve independently (row ``i`` needs only row ``i`` of ``F^(k-1)``,
    ``Lhat`` and ``alpha``), so the fill of ``sample_rows`` evenly spread rows, computed
    exactly (by the numba kernel on CPU, else by the torch ops), predicts the fill of the
    whole matrix at every scale. A row is bounded by its ``k``-ring and, after thresholding,
    by ``1 / threshold`` entries; what real meshes keep is far less (35 to 55 per row at the
    paper's settings), which is why the sample is used.

    The peak also counts the ``(K, V, 3)`` positions and coefficients a run returns, and the
    numba kernel's scratch rows.

    Args:
        ops: the mesh operators.
        num_scales: ``K``.
        threshold: ``lambda``.
        return_operators: all ``K`` operators are kept (else two at a time).
        budget: stop sampling as soon as the estimate exceeds this many bytes.
        sample_rows: rows to sample (all rows if the mesh has fewer).
        backend: one of :data:`BACKENDS`; the sample is stepped like the run (``"torch"``
            never touches the numba kernel, so nothing is compiled).
    """
    num_vertices = ops.num_vertices
    count = min(sample_rows, num_vertices)
    rows = torch.linspace(0, num_vertices - 1, count, device=ops.alpha.device).round().long()
    per_row = [int((ops.lhat.crow[rows + 1] - ops.lhat.crow[rows]).sum()) / count]  # Lhat's
    value_bytes = ops.alpha.element_size()
    entry_bytes = _INDEX_BYTES + value_bytes
    # Positions as computed, stacked, and the coefficients: three (K, V, 3) tensors.
    outputs = 3 * num_scales * num_vertices * 3 * value_bytes
    backend = resolve_backend(backend, ops.alpha.device)
    if backend == "numba":  # the kernel's scratch rows: two (V, LANES) and two byte rows
        per_thread = num_vertices * (2 * kernels.LANES * value_bytes + 2)
        outputs += torch.get_num_threads() * per_thread
    peak = 0.0
    with closing(_sample_steps(ops, rows, threshold, backend)) as steps:
        for _ in range(2, num_scales + 1):
            per_row.append(next(steps) / count)
            held = sum(per_row) if return_operators else per_row[-2] + _OUTPUT_SLACK * per_row[-1]
            peak = max(peak, _SAMPLE_MARGIN * held * num_vertices * entry_bytes + outputs)
            if budget is not None and peak > budget:
                return MemoryEstimate(int(peak), per_row, complete=False)
    return MemoryEstimate(int(peak), per_row, complete=True)


#: The split ``Lhat`` of each live ``Lhat`` given as CSR tensors, by their ``id`` and the
#: column index dtype, so that the memory estimate and the steps of a run, streamed or op by
#: op, split it once. An entry holds weak references to the tensors and their version
#: counters: it is used only for the same, unmodified tensors, and dropped when ``val`` is
#: freed.
_SPLIT_LHATS: dict[tuple, tuple[tuple, kernels.SplitLhat]] = {}


def _split_lhat(crow: Tensor, col: Tensor, val: Tensor, index) -> kernels.SplitLhat:
    """``Lhat`` given as CSR tensors, split for the kernel with ``index`` column indices
    (cached, see :data:`_SPLIT_LHATS`)."""
    tensors = (crow, col, val)
    key = (*map(id, tensors), np.dtype(index))
    versions = tuple(t._version for t in tensors)
    cached = _SPLIT_LHATS.get(key)
    if cached is not None:
        refs, cached_versions = cached[0]
        same = all(r() is t for r, t in zip(refs, tensors, strict=True))
        if same and cached_versions == versions:
            return cached[1]
    lhat = kernels.SplitLhat.from_csr(crow.numpy(), col.numpy(), val.numpy(), index)
    forget = lambda _, key=key: _SPLIT_LHATS.pop(key, None)  # noqa: E731
    refs = (weakref.ref(crow), weakref.ref(col), weakref.ref(val, forget))
    _SPLIT_LHATS[key] = ((refs, versions), lhat)
    return lhat


def _kernel_inputs(
    ops: MeshOperators, rows: Tensor | None = None
) -> tuple[kernels.SplitLhat, np.ndarray, kernels.Rows]:
    """``Lhat``, ``alpha`` and the rows ``rows`` (``(R,)`` int64, default all) of ``F^(1)``
    as the numba kernel takes them. Columns use :func:`~.kernels.index_dtype` everywhere, so
    that one compiled specialisation serves the memory estimate and the run."""
    lhat, alpha = _kernel_lhat(ops)
    picked = None if rows is None else rows.numpy()
    return lhat, alpha, kernels.first_rows(lhat, picked, lhat.w_col.dtype)


def _kernel_lhat(ops: MeshOperators) -> tuple[kernels.SplitLhat, np.ndarray]:
    """``Lhat`` split for the numba kernel (columns in :func:`~.kernels.index_dtype`) and
    ``alpha`` in its dtype."""
    index = kernels.index_dtype(ops.num_vertices)
    lhat = _split_lhat(ops.lhat.crow, ops.lhat.col, ops.lhat.val, index)
    return lhat, ops.alpha.numpy().astype(lhat.diagonal.dtype, copy=False)


def _sample_steps(ops: MeshOperators, rows: Tensor, threshold: float, backend: str
                  ) -> Iterator[int]:  # fmt: skip
    """Run the steps from the rows ``rows`` (``(R,)`` int64) of ``F^(1)``; yield the entries
    of each."""
    if backend != "numba":
        sample = normalize_rows(select_rows(ops.lhat, rows))
        while True:
            sample = diffusion_step(sample, ops, threshold)
            yield sample.nnz
    lhat, alpha, sample = _kernel_inputs(ops, rows)
    no_points = np.zeros((ops.num_vertices, 0), dtype=alpha.dtype)  # only the fill is wanted
    with kernel_buffers.WORKSPACES.borrow(
        ops.num_vertices, alpha.dtype, 0, sample.col.dtype
    ) as workspace:
        while True:
            sample, _, _ = kernels.fused_step(
                sample, lhat, alpha, float(threshold), no_points, 1, False, workspace
            )
            yield sample.nnz


def check_memory(
    ops: MeshOperators, num_scales: int, threshold: float, return_operators: bool,
    max_memory: int | None, backend: str = "auto",
) -> MemoryEstimate:  # fmt: skip
    """Raise :class:`MemoryBudgetError` if the run would exceed the budget; else the estimate."""
    budget = default_memory_budget() if max_memory is None else int(max_memory)
    estimate = estimate_memory(
        ops, num_scales, threshold, return_operators, budget=budget, backend=backend
    )
    if estimate.peak_bytes > budget:
        reached = len(estimate.entries_per_row)
        raise MemoryBudgetError(
            f"the operators for {ops.num_vertices} vertices at num_scales={num_scales}, "
            f"threshold={threshold:g} would need more than {estimate.peak_bytes / 2**30:.2f} GiB "
            f"(about {estimate.entries_per_row[-1]:.0f} entries per row by scale {reached}), "
            f"over the budget of {budget / 2**30:.2f} GiB. Raise the threshold, lower "
            f"num_scales, or raise the budget (max_memory=..., or ${MEMORY_ENV})."
        )
    return estimate


def _check_streamed_memory(ops: MeshOperators, num_scales: int, max_memory: int | None) -> None:
    """Raise :class:`MemoryBudgetError` if a streamed run would exceed the budget."""
    budget = default_memory_budget() if max_memory is None else int(max_memory)
    needed = streamed_memory(ops, num_scales)
    if needed > budget:
        raise MemoryBudgetError(
            f"a run on {ops.num_vertices} vertices at num_scales={num_scales} needs "
            f"{needed / 2**30:.2f} GiB for its outputs and scratch rows, over the budget of "
            f"{budget / 2**30:.2f} GiB. Lower num_scales, or raise the budget "
            f"(max_memory=..., or ${MEMORY_ENV})."
        )


def diffusion_step(previous: CSR, ops: MeshOperators, threshold: float) -> CSR:
    """``F^(k)`` from ``F^(k-1)``: ``[alpha ∘ T_lambda([F^(k-1) Lhat]_r)]_r`` with torch ops."""
    product = normalize_rows(csr_matmul(previous, ops.lhat))
    kept = threshold_rows(product, threshold)
    return normalize_rows(scale_columns(kept, ops.alpha.to(kept.val.dtype)))


def _torch_step(f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points,
                sort_columns=True):  # fmt: skip
    """The fused step's contract, composed from the separate ``stochlap`` ops (always sorted)."""
    previous = CSR(f_crow, f_col, f_val, int(l_crow.shape[0]) - 1)
    lhat = CSR(l_crow, l_col, l_val, previous.num_cols)
    following = diffusion_step(previous, MeshOperators(lhat, alpha), threshold)
    difference = row_abs_diff_sum(following, previous)
    return following.crow, following.col, following.val, difference, spmm(following, points)


def _fused_step_fake(f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points,
                     sort_columns=True):  # fmt: skip
    return (
        *dynamic_csr_like(f_crow, f_col, f_val),
        f_val.new_empty(f_crow.shape[0] - 1), points.new_empty(points.shape),
    )  # fmt: skip


def _fused_step_cpu(f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points,
                    sort_columns=True):  # fmt: skip
    """The CPU kernel of ``stochlap::diffusion_step``: the numba kernel when available."""
    if not kernels.available():
        return _torch_step(f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points)
    dtype = f_val.numpy().dtype
    rows, difference, moved = kernels.fused_step(
        kernels.Rows.from_csr(f_crow.numpy(), f_col.numpy(), f_val.numpy()),
        _split_lhat(l_crow, l_col, l_val, l_col.numpy().dtype),
        alpha.numpy().astype(dtype, copy=False),
        float(threshold), points.numpy().astype(dtype, copy=False), torch.get_num_threads(),
        sort_columns,
    )  # fmt: skip
    return (*(torch.from_numpy(a) for a in rows.to_csr()), torch.from_numpy(difference),
            torch.from_numpy(moved))  # fmt: skip


@define_op(
    "diffusion_step(Tensor f_crow, Tensor f_col, Tensor f_val, Tensor l_crow, Tensor l_col, "
    "Tensor l_val, Tensor alpha, float threshold, Tensor points, bool sort_columns=True) "
    "-> (Tensor, Tensor, Tensor, Tensor, Tensor)",
    fake=_fused_step_fake,
    cpu=_fused_step_cpu,
)
def _fused_step_op(
    f_crow: Tensor, f_col: Tensor, f_val: Tensor,
    l_crow: Tensor, l_col: Tensor, l_val: Tensor,
    alpha: Tensor, threshold: float, points: Tensor, sort_columns: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:  # fmt: skip
    """One step: ``F^(k)`` as ``(crow, col, val)``, ``D^(k)`` ``(V,)`` and ``F^(k) P``.

    With ``sort_columns=False`` the columns within a row may come in any order.
    """
    return _torch_step(f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points)


def resolve_backend(backend: str, device: torch.device) -> str:
    """``"numba"`` or ``"torch"`` for ``backend`` in :data:`BACKENDS` on ``device``."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "numba" and (device.type != "cpu" or not kernels.available()):
        raise ValueError("backend='numba' needs CPU tensors and numba installed")
    if backend == "auto":
        return "numba" if device.type == "cpu" and kernels.available() else "torch"
    return backend


def fused_step(
    previous: CSR, ops: MeshOperators, threshold: float, points: Tensor, backend: str,
    sort_columns: bool = True,
) -> tuple[CSR, Tensor, Tensor]:  # fmt: skip
    """``(F^(k), D^(k), F^(k) P)`` from ``F^(k-1)``, with ``points`` ``(V, C)`` detached."""
    args = (previous.crow, previous.col, previous.val, ops.lhat.crow, ops.lhat.col,
            ops.lhat.val, ops.alpha, float(threshold), points)  # fmt: skip
    if backend == "numba":
        crow, col, val, difference, moved = torch.ops.stochlap.diffusion_step(*args, sort_columns)
    else:
        crow, col, val, difference, moved = _torch_step(*args)
    return CSR(crow, col, val, previous.num_cols), difference, moved


def _prefaulted_zeros(shape: tuple[int, ...], dtype: torch.dtype) -> Tensor:
    """``torch.zeros(shape, dtype=dtype)`` on the CPU, its pages touched before the kernel runs
    (:func:`~.kernel_buffers.prefaulted_zeros`; torch's allocator would leave the first touch
    to the parallel kernel: 45 ms of a 185 ms run on a 50k-vertex mesh)."""
    numpy_dtype = torch.empty(0, dtype=dtype).numpy().dtype
    threads = torch.get_num_threads()
    return torch.from_numpy(kernel_buffers.prefaulted_zeros(shape, numpy_dtype, threads))


def _streamed_steps(
    ops: MeshOperators, points: Tensor, num_scales: int, threshold: float,
    progress: ProgressCallback | None, order: Tensor | None,
) -> tuple[Tensor, Tensor, list[int]]:  # fmt: skip
    """Steps ``2..K`` with the numba kernel, a block of rows through every step at a time.

    Rows evolve independently, so no ``F^(k)`` is ever stored (:func:`~.kernels.stream_steps`):
    besides the outputs, a run holds ``Lhat`` and a few rows per thread. With a ``progress``
    callback the rows go to the kernel in ``K - 1`` slices, and ``progress(k, K)`` is called
    after the ``(k - 1)``-th; without one, in a single call. The
    kernel writes each row's results straight into row ``order[i]`` of the outputs (``i`` when
    ``order`` is ``None``).

    Args:
        ops: the operators of the (renumbered) mesh.
        points: ``(V, 3)`` positions of the renumbered mesh, no grad.
        order: ``(V,)`` original index of each renumbered vertex, or ``None``.

    Returns:
        ``(positions, differences, entries)``: ``(K, V, 3)`` and ``(K, V)`` in the original
        vertex order (``positions[0]`` is the input), and the ``K`` entry counts.
    """
    num_vertices = ops.num_vertices
    lhat, alpha = _kernel_lhat(ops)  # the kernel takes F^(1) from Lhat, row by row
    moved = points.numpy().astype(alpha.dtype, copy=False)
    target = None if order is None else order.numpy()
    positions = _prefaulted_zeros((num_scales, num_vertices, 3), points.dtype)
    if order is None:
        positions[0] = points
    else:
        positions[0].index_copy_(0, order, points)
    differences = _prefaulted_zeros((num_scales, num_vertices), points.dtype)
    # Slices only serve progress reports; without a callback the rows go in one call.
    slices = num_scales - 1 if progress is not None else 1
    blocks = -(-num_vertices // kernels.LANES)
    bounds = np.minimum(np.linspace(0, blocks, slices + 1).round().astype(np.int64) * kernels.LANES,
                        num_vertices)  # fmt: skip
    entries = np.zeros(num_scales - 1, dtype=np.int64)
    pool = kernel_buffers.WORKSPACES
    with pool.borrow(num_vertices, alpha.dtype, 0, lhat.w_col.dtype) as workspace:
        for piece in range(slices):
            rows = (int(bounds[piece]), int(bounds[piece + 1]))
            if rows[1] > rows[0]:
                entries += kernels.stream_steps(
                    lhat, alpha, float(threshold), moved, torch.get_num_threads(), rows,
                    differences.numpy(), positions.numpy(), target, workspace,
                )  # fmt: skip
            if progress is not None:
                progress(piece + 2, num_scales)
    for k, count in enumerate(entries.tolist(), start=2):
        logger.debug("scale %d/%d: %.1f entries per row", k, num_scales, count / num_vertices)
    return positions, differences, [ops.lhat.nnz, *entries.tolist()]


def streamed_memory(ops: MeshOperators, num_scales: int) -> int:
    """Bytes a streamed run (:func:`_streamed_steps`) adds to its operators: the ``(K, V, 3)``
    positions, the ``(K, V)`` differences (coefficients come on first access), ``Lhat`` split
    for the kernel and the kernel's scratch rows."""
    value_bytes = ops.alpha.element_size()
    num_vertices = ops.num_vertices
    outputs = num_scales * num_vertices * (3 + 1) * value_bytes
    index_bytes = np.dtype(kernels.index_dtype(num_vertices)).itemsize
    split = ((ops.lhat.nnz - num_vertices) * (index_bytes + value_bytes)
             + num_vertices * (8 + 2 * value_bytes))  # fmt: skip
    per_thread = num_vertices * (2 * kernels.LANES * value_bytes + 2)
    return outputs + split + torch.get_num_threads() * per_thread


def multiscale_representation(
    vertices,
    faces,
    num_scales: int = 8,
    threshold: float = 1e-3,
    return_operators: bool = False,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    backend: str = "auto",
    batch: Tensor | None = None,
) -> MultiscaleRepresentation:
    """Multiscale representation of a mesh (Algorithm 1) with the difference maps of Alg. 2.

    Args:
        vertices: ``(V, 3)`` float tensor; its dtype and device are kept throughout. Gradients
            flow into ``positions`` through ``P^(k) = F^(k) P`` with the operators held
            constant. Meshes of :data:`~stochlap_torch.operators.LOCALITY_MIN_VERTICES` or
            more are processed in a cache-friendly vertex order internally; every output is
            in the input's order.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``; entries of the normalised product below it are
            dropped at every step.
        return_operators: keep all ``F^(k)`` (costs ``K`` times the memory of one).
        max_memory: byte budget for the operators; defaults to :func:`default_memory_budget`.
        progress: called as ``progress(k, K)`` after each scale; on the streamed CPU path,
            where a row goes through every scale at once, after each ``(K - 1)``-th of the
            rows.
        backend: one of :data:`BACKENDS`.
        batch: optional ``(V,)`` int64 mesh index of every vertex when ``vertices`` and
            ``faces`` pack several meshes (:class:`~stochlap_torch.batch.MeshBatch`); every
            per-vertex output then equals that of a separate run on each mesh.

    Raises:
        MeshError: bad input mesh.
        ValueError: bad ``num_scales`` or ``threshold``.
        MemoryBudgetError: the operators would not fit the budget.
    """
    check_parameters(num_scales, threshold)
    # Zero-length edges are caught where the weights are built (abs_laplacian).
    points, faces = as_mesh_tensors(vertices, faces, check_edge_lengths=False)
    backend = resolve_backend(backend, points.device)
    num_vertices = points.shape[0]
    if batch is not None:
        batch = check_batch(batch.to(points.device), num_vertices, faces)
    # Large meshes: work in a cache-friendly vertex order, hand results back in file order.
    order = locality_order(points.detach()) if num_vertices >= LOCALITY_MIN_VERTICES else None
    try:
        return _run_steps(
            points, faces, batch, order, num_scales, threshold, return_operators, max_memory,
            progress, backend,
        )  # fmt: skip
    except MeshError:
        if order is not None:
            validate_mesh(points, faces)  # the same error, in the caller's vertex numbering
        raise


def _run_steps(
    points: Tensor,
    faces: Tensor,
    batch: Tensor | None,
    order: Tensor | None,
    num_scales: int,
    threshold: float,
    return_operators: bool,
    max_memory: int | None,
    progress: ProgressCallback | None,
    backend: str,
) -> MultiscaleRepresentation:
    """Algorithm 1 on a validated mesh, renumbered by ``order`` (if given) for the steps;
    every output is in the input's vertex order (``backend`` resolved)."""
    if order is None:
        new_index = None
        work_points, work_faces, work_batch = points, faces, batch
    else:
        new_index = torch.empty_like(order)
        new_index[order] = torch.arange(order.shape[0], device=order.device)
        work_points, work_faces = points[order], new_index[faces]
        work_batch = None if batch is None else batch[order]
    with torch.no_grad():
        ops = operators_of_valid_mesh(work_points.detach(), work_faces, work_batch)
    streamed = backend == "numba" and not return_operators and not points.requires_grad
    if streamed:
        _check_streamed_memory(ops, num_scales, max_memory)
    else:
        check_memory(ops, num_scales, threshold, return_operators, max_memory, backend)
    if progress is not None:
        progress(1, num_scales)

    if streamed:
        # No operator outlives its row block: rows go through every step, block by block.
        positions, differences, entries = _streamed_steps(
            ops, work_points.detach(), num_scales, threshold, progress, order
        )
        operators = None
    else:
        positions, differences, entries, operators = _stepped(
            ops, ops.stochastic_laplacian(), work_points, num_scales, threshold,
            return_operators, progress, backend,
        )  # fmt: skip
        if new_index is not None:
            positions, differences = positions[:, new_index], differences[:, new_index]
            if operators is not None:
                operators = [permute_csr(op, order) for op in operators]
    return MultiscaleRepresentation(
        positions=positions,
        differences=differences,
        entries=torch.tensor(entries, dtype=torch.int64),
        operators=None if operators is None else [op.to_sparse_csr() for op in operators],
        batch=batch,
    )


def _stepped(
    ops: MeshOperators, current: CSR, points: Tensor, num_scales: int, threshold: float,
    return_operators: bool, progress: ProgressCallback | None, backend: str,
) -> tuple[Tensor, Tensor, list[int], list[CSR] | None]:  # fmt: skip
    """Steps ``2..K`` one op call at a time, in the order of ``points``; with gradients
    through ``P^(k) = F^(k) P`` and, if asked, every ``F^(k)`` kept.

    Returns:
        ``(positions, differences, entries, operators)``: ``(K, V, 3)``, ``(K, V)``, the
        ``K`` entry counts and ``F^(1..K)`` (or ``None``).
    """
    positions, differences = [points], [points.new_zeros(ops.num_vertices)]
    entries = [current.nnz]
    operators = [current] if return_operators else None
    for k in range(2, num_scales + 1):
        with torch.no_grad():
            following, difference, moved = fused_step(
                current, ops, threshold, points.detach(), backend, return_operators
            )
        differences.append(difference)
        # Gradients reach the input through P^(k) = F^(k) P with F^(k) held constant.
        positions.append(spmm(following, points) if points.requires_grad else moved)
        entries.append(following.nnz)
        if operators is not None:
            operators.append(following)
        logger.debug(
            "scale %d/%d: %.1f entries per row", k, num_scales, following.nnz / ops.num_vertices
        )
        current = following
        if progress is not None:
            progress(k, num_scales)
    return torch.stack(positions), torch.stack(differences), entries, operators

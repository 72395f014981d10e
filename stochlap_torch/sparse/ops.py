"""Sparse CSR operators as registered torch operators (namespace ``stochlap``), and the
differentiable row operations their kernels are. Their kernels are plain torch (any device)
and take the components of a :class:`~.csr.CSR` as ordinary tensors (torch's fake-tensor
machinery does not accept ``torch.sparse_csr`` inputs).
"""

from __future__ import annotations

import torch
from torch import Tensor

from .._common.tensors import unique_with_inverse
from .csr import CSR, compress_rows, product_terms, row_ids, work_blocks
from .registry import define_op

__all__ = [
    "csr_matmul",
    "normalize_rows",
    "row_abs_diff_sum",
    "scale_columns",
    "spmm",
    "threshold_rows",
]

#: Upper bound on the scalar products one block of :func:`csr_matmul` expands at once.
BLOCK_PRODUCTS = 1 << 22


def _coalesce(rows: Tensor, cols: Tensor, vals: Tensor, num_cols: int):
    """Sum duplicate ``(row, col)`` entries; return sorted ``(rows, cols, vals)``."""
    keys = rows * num_cols + cols
    unique_keys, inverse = unique_with_inverse(keys)
    summed = vals.new_zeros(unique_keys.shape[0]).index_add_(0, inverse, vals)
    return unique_keys // num_cols, unique_keys % num_cols, summed


def dynamic_csr_like(crow: Tensor, col: Tensor, val: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Fake ``(crow, col, val)`` with ``crow``'s shape and a data-dependent number of entries:
    the output of an operator whose sparsity pattern is only known after it ran."""
    nnz = torch.library.get_ctx().new_dynamic_size()
    return crow.new_empty(crow.shape), col.new_empty(nnz), val.new_empty(nnz)


@define_op(
    "csr_matmul(Tensor a_crow, Tensor a_col, Tensor a_val, Tensor b_crow, Tensor b_col, "
    "Tensor b_val, SymInt num_cols) -> (Tensor, Tensor, Tensor)",
    fake=lambda *args: dynamic_csr_like(*args[:3]),
)
def _csr_matmul_op(a_crow, a_col, a_val, b_crow, b_col, b_val, num_cols):
    num_rows = a_crow.shape[0] - 1
    products = (b_crow[a_col + 1] - b_crow[a_col]).to(torch.int64)
    entry_rows = row_ids(a_crow, a_col.shape[0])
    per_row = a_val.new_zeros(num_rows, dtype=torch.int64).index_add_(0, entry_rows, products)
    parts = []
    for start, stop in work_blocks(per_row, BLOCK_PRODUCTS):
        lo, hi = int(a_crow[start]), int(a_crow[stop])
        source, b_index = product_terms(a_col[lo:hi], b_crow)
        values = a_val[lo:hi][source] * b_val[b_index]
        parts.append(_coalesce(entry_rows[lo:hi][source], b_col[b_index], values, num_cols))
    if not parts:
        return a_crow.new_zeros(1), a_col.new_zeros(0), a_val.new_zeros(0)
    rows, cols, vals = (torch.cat(p) for p in zip(*parts, strict=True))
    return compress_rows(rows, num_rows), cols, vals


def csr_matmul(a: CSR, b: CSR) -> CSR:
    """Sparse product ``a @ b`` (``a`` is ``(n, m)``, ``b`` is ``(m, p)``)."""
    crow, col, val = torch.ops.stochlap.csr_matmul(
        a.crow, a.col, a.val, b.crow, b.col, b.val, b.num_cols
    )
    return CSR(crow, col, val, b.num_cols)


@define_op(
    "threshold_rows(Tensor crow, Tensor col, Tensor val, float threshold) "
    "-> (Tensor, Tensor, Tensor)",
    fake=lambda crow, col, val, threshold: dynamic_csr_like(crow, col, val),
)
def _threshold_rows_op(crow, col, val, threshold):
    rows = row_ids(crow, col.shape[0])
    row_max = val.new_full((crow.shape[0] - 1,), -torch.inf).scatter_reduce_(
        0, rows, val, reduce="amax"
    )
    keep = (val >= threshold) | (val == row_max[rows])
    return compress_rows(rows[keep], crow.shape[0] - 1), col[keep], val[keep]


def threshold_rows(matrix: CSR, threshold: float) -> CSR:
    """Drop entries strictly below ``threshold``, as Algorithm 1 does; each row's largest
    entry is always kept (a normalised row may hold none above a threshold over
    ``1 / row_nnz``)."""
    crow, col, val = torch.ops.stochlap.threshold_rows(
        matrix.crow, matrix.col, matrix.val, float(threshold)
    )
    return CSR(crow, col, val, matrix.num_cols)


@define_op(
    "normalize_rows(Tensor crow, Tensor val) -> Tensor",
    fake=lambda crow, val: torch.empty_like(val),
)
def row_normalise(crow: Tensor, val: Tensor) -> Tensor:
    """Differentiable ``[.]_r``: the ``(nnz,)`` values of a CSR, each row divided by its sum
    (the kernel of the ``normalize_rows`` operator)."""
    rows = row_ids(crow, val.shape[0])
    sums = val.new_zeros(crow.shape[0] - 1).index_add_(0, rows, val)
    return val / sums[rows]


def normalize_rows(matrix: CSR) -> CSR:
    """Divide each row by its sum (rows must hold positive values), ``[.]_r`` in the paper."""
    return matrix.with_values(torch.ops.stochlap.normalize_rows(matrix.crow, matrix.val))


@define_op(
    "scale_columns(Tensor col, Tensor val, Tensor scale) -> Tensor",
    fake=lambda col, val, scale: torch.empty_like(val),
)
def _scale_columns_op(col, val, scale):
    return val * scale[col]


def scale_columns(matrix: CSR, scale: Tensor) -> CSR:
    """Multiply column ``j`` by ``scale[j]``, ``(num_cols,)``: the Schur product ``alpha ∘ F``."""
    return matrix.with_values(torch.ops.stochlap.scale_columns(matrix.col, matrix.val, scale))


def row_abs_diff(a: CSR, b: CSR) -> Tensor:
    """Differentiable ``(n,)`` row sums of ``|a - b|`` over the union of the two patterns."""
    rows = torch.cat([row_ids(a.crow, a.nnz), row_ids(b.crow, b.nnz)])
    cols = torch.cat([a.col, b.col])
    diff_rows, _, diff = _coalesce(rows, cols, torch.cat([a.val, -b.val]), a.num_cols)
    return a.val.new_zeros(a.num_rows).index_add_(0, diff_rows, diff.abs())


@define_op(
    "row_abs_diff_sum(Tensor a_crow, Tensor a_col, Tensor a_val, Tensor b_crow, Tensor b_col, "
    "Tensor b_val, SymInt num_cols) -> Tensor",
    fake=lambda a_crow, *args: args[1].new_empty(a_crow.shape[0] - 1),
)
def _row_abs_diff_sum_op(a_crow, a_col, a_val, b_crow, b_col, b_val, num_cols):
    return row_abs_diff(CSR(a_crow, a_col, a_val, num_cols), CSR(b_crow, b_col, b_val, num_cols))


def row_abs_diff_sum(a: CSR, b: CSR) -> Tensor:
    """``(n,)`` row sums of ``|a - b|`` for two CSR matrices with different patterns."""
    return torch.ops.stochlap.row_abs_diff_sum(
        a.crow, a.col, a.val, b.crow, b.col, b.val, a.num_cols
    )


def _spmm_backward(ctx, grad_out):
    """Edge-list gathers: O(nnz) memory, never a dense ``(n, m)`` gradient."""
    crow, col, val, dense = ctx.saved_tensors
    rows = row_ids(crow, col.shape[0])
    grad_val = grad_dense = None
    if ctx.needs_input_grad[2]:
        grad_val = (grad_out[rows] * dense[col]).sum(dim=1)
    if ctx.needs_input_grad[3]:
        grad_dense = torch.zeros_like(dense).index_add_(0, col, val.unsqueeze(1) * grad_out[rows])
    return None, None, grad_val, grad_dense


@define_op(
    "spmm(Tensor crow, Tensor col, Tensor val, Tensor dense) -> Tensor",
    fake=lambda crow, col, val, dense: dense.new_empty(crow.shape[0] - 1, dense.shape[1]),
    backward=_spmm_backward,
    setup_context=lambda ctx, inputs, output: ctx.save_for_backward(*inputs),
)
def _spmm_op(crow, col, val, dense):
    rows = row_ids(crow, col.shape[0])
    out = dense.new_zeros(crow.shape[0] - 1, dense.shape[1])
    return out.index_add_(0, rows, val.unsqueeze(1) * dense[col])


def spmm(matrix: CSR, dense: Tensor) -> Tensor:
    """``matrix @ dense`` for ``(m, C)`` dense, differentiable w.r.t. values and ``dense``."""
    return torch.ops.stochlap.spmm(matrix.crow, matrix.col, matrix.val, dense)

"""Differentiable sparse operations on fixed patterns, with ``O(nnz)`` saved memory.

torch's sparse autograd on the CPU builds dense ``V x V`` gradients for products of sparse
matrices; these operate on CSR values with gathers and ``index_add`` instead. The product has
its own :class:`torch.autograd.Function` that saves only the two operands and recomputes the
expansion (one term per pair of stored entries) in bounded blocks in the backward pass.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .csr import CSR, row_ids, work_blocks

__all__ = [
    "EXPANSION_BLOCK",
    "constant_matmul",
    "csr_keys",
    "kept_entries",
    "pattern_matmul",
    "row_abs_diff",
    "row_normalise",
]

#: Upper bound on the product terms one block of :func:`pattern_matmul` expands at once.
EXPANSION_BLOCK = 1 << 22


def _expansion(a: CSR, b: CSR, c_keys: Tensor, start: int, stop: int):
    """Product terms of ``a @ b`` for stored entries ``[start, stop)`` of ``a``.

    Returns ``(a_index, b_index, c_index)`` ``(T,)`` int64: term ``t`` is
    ``a.val[a_index[t]] * b.val[b_index[t]]`` and lands on entry ``c_index[t]`` of the product
    pattern whose sorted ``row * num_cols + col`` keys are ``c_keys``.
    """
    device = a.col.device
    a_rows = row_ids(a.crow, a.nnz)[start:stop]
    a_col = a.col[start:stop]
    counts = b.crow[a_col + 1] - b.crow[a_col]
    total = int(counts.sum())
    local = torch.repeat_interleave(
        torch.arange(stop - start, device=device), counts, output_size=total
    )
    first = torch.cumsum(counts, dim=0) - counts
    b_index = b.crow[a_col[local]] + torch.arange(total, device=device) - first[local]
    keys = a_rows[local] * b.num_cols + b.col[b_index]
    c_index = torch.searchsorted(c_keys, keys)
    return local + start, b_index, c_index


def csr_keys(matrix: CSR) -> Tensor:
    """``(nnz,)`` sorted ``row * num_cols + col`` keys of a row-major CSR with sorted columns."""
    return row_ids(matrix.crow, matrix.nnz) * matrix.num_cols + matrix.col


class _PatternMatmul(torch.autograd.Function):
    """Values of ``a @ b`` on a given pattern; saves operands, recomputes terms per block."""

    @staticmethod
    def forward(ctx, a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys, num_cols):
        a = CSR(a_crow, a_col, a_val, int(b_crow.shape[0]) - 1)
        b = CSR(b_crow, b_col, b_val, num_cols)
        out = a_val.new_zeros(c_keys.shape[0])
        for start, stop in work_blocks(b_crow[a_col + 1] - b_crow[a_col], EXPANSION_BLOCK):
            a_index, b_index, c_index = _expansion(a, b, c_keys, start, stop)
            out.index_add_(0, c_index, a_val[a_index] * b_val[b_index])
        ctx.save_for_backward(a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys)
        ctx.num_cols = num_cols
        return out

    @staticmethod
    def backward(ctx, grad_out):
        a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys = ctx.saved_tensors
        a = CSR(a_crow, a_col, a_val, int(b_crow.shape[0]) - 1)
        b = CSR(b_crow, b_col, b_val, ctx.num_cols)
        grad_a = torch.zeros_like(a_val) if ctx.needs_input_grad[0] else None
        grad_b = torch.zeros_like(b_val) if ctx.needs_input_grad[1] else None
        for start, stop in work_blocks(b_crow[a_col + 1] - b_crow[a_col], EXPANSION_BLOCK):
            a_index, b_index, c_index = _expansion(a, b, c_keys, start, stop)
            upstream = grad_out[c_index]
            if grad_a is not None:
                grad_a.index_add_(0, a_index, upstream * b_val[b_index])
            if grad_b is not None:
                grad_b.index_add_(0, b_index, upstream * a_val[a_index])
        return grad_a, grad_b, None, None, None, None, None, None


def pattern_matmul(a: CSR, b: CSR, pattern: CSR) -> Tensor:
    """``(nnz,)`` values of ``a @ b`` on ``pattern`` (which must hold every product entry).

    Differentiable w.r.t. ``a.val`` and ``b.val`` in ``O(nnz)`` saved memory.
    """
    return _PatternMatmul.apply(
        a.val, b.val, a.crow, a.col, b.crow, b.col, csr_keys(pattern), b.num_cols
    )


class _ConstantMatmul(torch.autograd.Function):
    """``matrix @ dense`` for a constant ``torch.sparse_csr`` matrix given with its transpose:
    the backward pass is one product with the transpose (torch's own would transpose the
    matrix on every call)."""

    @staticmethod
    def forward(ctx, dense: Tensor, matrix: Tensor, transpose: Tensor) -> Tensor:
        ctx.matrix, ctx.transpose = matrix, transpose
        return matrix @ dense

    @staticmethod
    def backward(ctx, grad: Tensor):
        return _ConstantMatmul.apply(grad, ctx.transpose, ctx.matrix), None, None


def constant_matmul(matrix: Tensor, transpose: Tensor, dense: Tensor) -> Tensor:
    """``(m, C)`` ``matrix @ dense`` for a constant ``(m, n)`` ``torch.sparse_csr`` matrix,
    its ``(n, m)`` ``transpose`` and ``(n, C)`` ``dense`` (in the matrix's dtype, on its
    device); differentiable w.r.t. ``dense``, to any order."""
    return _ConstantMatmul.apply(dense, matrix, transpose)


def row_normalise(crow: Tensor, val: Tensor) -> Tensor:
    """Differentiable ``[.]_r``: each row of a CSR divided by its sum."""
    rows = row_ids(crow, val.shape[0])
    sums = val.new_zeros(crow.shape[0] - 1).index_add(0, rows, val)
    return val / sums[rows]


def row_abs_diff(a: CSR, b: CSR) -> Tensor:
    """Differentiable ``(V,)`` ``sum_j |a - b|(i, j)`` over the union of the two patterns."""
    keys = torch.cat([csr_keys(a), csr_keys(b)])
    unique, inverse = torch.unique(keys, sorted=True, return_inverse=True)
    values = torch.cat([a.val, -b.val])
    difference = values.new_zeros(unique.shape[0]).index_add(0, inverse, values)
    rows = torch.div(unique, a.num_cols, rounding_mode="floor")
    return values.new_zeros(a.num_rows).index_add(0, rows, difference.abs())


def kept_entries(product: CSR, kept: CSR) -> Tensor:
    """``(nnz_kept,)`` positions in ``product`` of the entries of ``kept`` (a sub-pattern)."""
    return torch.searchsorted(csr_keys(product), csr_keys(kept))

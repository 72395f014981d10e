"""Differentiable sparse products on fixed patterns, with ``O(nnz)`` saved memory (torch's
sparse autograd on the CPU builds dense ``V x V`` gradients): :func:`pattern_matmul` saves only
the two operands and recomputes the terms in bounded blocks in the backward pass.
"""

from __future__ import annotations

import torch
from torch import Tensor

# constant_matmul, row_abs_diff and row_normalise: importable from here too.
from .csr import CSR, constant_matmul, csr_keys, product_terms, row_ids, work_blocks  # noqa: F401
from .ops import row_abs_diff, row_normalise  # noqa: F401

__all__ = ["pattern_matmul"]

#: Upper bound on the product terms one block of :func:`pattern_matmul` expands at once.
EXPANSION_BLOCK = 1 << 22


def _terms(a_crow, a_col, b_crow, b_col, c_keys, num_cols):
    """Per block of about :data:`EXPANSION_BLOCK` terms of ``a @ b``: ``(a_index, b_index,
    c_index)`` ``(T,)`` int64, term ``t`` being ``a_val[a_index[t]] * b_val[b_index[t]]``,
    landing on entry ``c_index[t]`` of the product pattern of sorted keys ``c_keys``."""
    entry_rows = row_ids(a_crow, a_col.shape[0])
    for start, stop in work_blocks(b_crow[a_col + 1] - b_crow[a_col], EXPANSION_BLOCK):
        source, b_index = product_terms(a_col[start:stop], b_crow)
        keys = entry_rows[start:stop][source] * num_cols + b_col[b_index]
        yield source + start, b_index, torch.searchsorted(c_keys, keys)


class _PatternMatmul(torch.autograd.Function):
    """Values of ``a @ b`` on a given pattern; saves operands, recomputes terms per block."""

    @staticmethod
    def forward(ctx, a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys, num_cols):
        out = a_val.new_zeros(c_keys.shape[0])
        for a_index, b_index, c_index in _terms(a_crow, a_col, b_crow, b_col, c_keys, num_cols):
            out.index_add_(0, c_index, a_val[a_index] * b_val[b_index])
        ctx.save_for_backward(a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys)
        ctx.num_cols = num_cols
        return out

    @staticmethod
    def backward(ctx, grad_out):
        a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys = ctx.saved_tensors
        grad_a = torch.zeros_like(a_val) if ctx.needs_input_grad[0] else None
        grad_b = torch.zeros_like(b_val) if ctx.needs_input_grad[1] else None
        terms = _terms(a_crow, a_col, b_crow, b_col, c_keys, ctx.num_cols)
        for a_index, b_index, c_index in terms:
            upstream = grad_out[c_index]
            if grad_a is not None:
                grad_a.index_add_(0, a_index, upstream * b_val[b_index])
            if grad_b is not None:
                grad_b.index_add_(0, b_index, upstream * a_val[a_index])
        return grad_a, grad_b, None, None, None, None, None, None


def pattern_matmul(a: CSR, b: CSR, pattern: CSR) -> Tensor:
    """``(nnz,)`` values of ``a @ b`` on ``pattern`` (which must hold every product entry),
    differentiable w.r.t. ``a.val`` and ``b.val`` in ``O(nnz)`` saved memory."""
    return _PatternMatmul.apply(
        a.val, b.val, a.crow, a.col, b.crow, b.col, csr_keys(pattern), b.num_cols
    )


def kept_entries(product: CSR, kept: CSR) -> Tensor:
    """``(nnz_kept,)`` positions in ``product`` of the entries of ``kept`` (a sub-pattern)."""
    return torch.searchsorted(csr_keys(product), csr_keys(kept))

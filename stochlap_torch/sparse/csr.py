"""The CSR container, the structural helpers the operators and steps share, and the product of
a constant ``torch.sparse_csr`` matrix with a dense one."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = [
    "CSR",
    "compress_rows",
    "constant_matmul",
    "permute_csr",
    "row_ids",
    "select_rows",
    "slice_rows",
    "symmetric_csr",
    "work_blocks",
]


@dataclass(frozen=True)
class CSR:
    """A sparse matrix in compressed-row form; converts to ``torch.sparse_csr`` at the public
    boundary.

    Attributes:
        crow: ``(n + 1,)`` int64 row pointers.
        col: ``(nnz,)`` int64 column indices, sorted within each row.
        val: ``(nnz,)`` float values.
        num_cols: number of columns.
    """

    crow: Tensor
    col: Tensor
    val: Tensor
    num_cols: int

    @property
    def num_rows(self) -> int:
        return int(self.crow.shape[0]) - 1

    @property
    def nnz(self) -> int:
        return int(self.col.shape[0])

    def with_values(self, val: Tensor) -> CSR:
        """The same pattern with new ``(nnz,)`` values."""
        return CSR(self.crow, self.col, val, self.num_cols)

    def to_sparse_csr(self, compact: bool = False) -> Tensor:
        """As a ``torch.sparse_csr`` tensor of shape ``(num_rows, num_cols)``; with
        ``compact``, int32 indices where they fit (MKL and cuSPARSE convert int64 ones on every
        product)."""
        crow, col = self.crow, self.col
        if compact and max(self.nnz, self.num_cols, self.num_rows) <= torch.iinfo(torch.int32).max:
            crow, col = crow.to(torch.int32), col.to(torch.int32)
        with warnings.catch_warnings():  # nothing a user can act on
            warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
            size = (self.num_rows, self.num_cols)
            return torch.sparse_csr_tensor(crow, col, self.val, size=size, check_invariants=False)

    @classmethod
    def from_sparse_csr(cls, matrix: Tensor) -> CSR:
        return cls(
            matrix.crow_indices(), matrix.col_indices(), matrix.values(), int(matrix.shape[1])
        )

    def to_dense(self) -> Tensor:
        """``(num_rows, num_cols)`` dense copy, for tests and small matrices."""
        dense = self.val.new_zeros(self.num_rows, self.num_cols)
        dense[row_ids(self.crow), self.col] = self.val
        return dense


def row_ids(crow: Tensor, nnz: int | None = None) -> Tensor:
    """Row index of every stored entry: ``(nnz,)`` int64 from ``(n + 1,)`` row pointers
    (``nnz``: ``crow[-1]`` if known, which spares a device sync; ``None``: found here)."""
    counts = crow.diff()
    rows = torch.arange(counts.shape[0], device=crow.device)
    return torch.repeat_interleave(rows, counts, output_size=nnz)


def csr_keys(matrix: CSR) -> Tensor:
    """``(nnz,)`` sorted ``row * num_cols + col`` keys of a row-major CSR with sorted columns."""
    return row_ids(matrix.crow, matrix.nnz) * matrix.num_cols + matrix.col


def compress_rows(rows: Tensor, num_rows: int) -> Tensor:
    """Row pointers ``(num_rows + 1,)`` from sorted ``(nnz,)`` row indices."""
    return _pointers(torch.bincount(rows, minlength=num_rows))


def _pointers(counts: Tensor) -> Tensor:
    """``(n + 1,)`` int64 row pointers of ``(n,)`` entry counts."""
    crow = torch.zeros(counts.shape[0] + 1, dtype=torch.int64, device=counts.device)
    torch.cumsum(counts, dim=0, out=crow[1:])
    return crow


def product_terms(a_col: Tensor, b_crow: Tensor) -> tuple[Tensor, Tensor]:
    """The terms of a sparse product ``a @ b`` from the stored entries ``a_col`` ``(n,)`` of
    ``a``: ``(source (T,), b_index (T,))`` int64, term ``t`` multiplies entry ``source[t]`` of
    ``a_col`` with stored entry ``b_index[t]`` of ``b`` (``b_crow`` its row pointers)."""
    counts = b_crow[a_col + 1] - b_crow[a_col]
    total = int(counts.sum())
    source = torch.repeat_interleave(
        torch.arange(a_col.shape[0], device=a_col.device), counts, output_size=total
    )
    first = torch.cumsum(counts, dim=0) - counts
    offset = torch.arange(total, device=a_col.device) - first[source]
    return source, b_crow[a_col[source]] + offset


def permute_csr(matrix: CSR, new_index: Tensor) -> CSR:
    """Relabel rows and columns of a square ``(n, n)`` CSR by the ``(n,)`` int64 permutation
    ``new_index[old] = new``: entry ``(i, j)`` moves to ``(new[i], new[j])``, columns sorted
    within each row."""
    n = matrix.num_rows
    rows = new_index[row_ids(matrix.crow, matrix.nnz)]
    cols = new_index[matrix.col]
    order = torch.argsort(rows * n + cols)
    return CSR(compress_rows(rows[order], n), cols[order], matrix.val[order], matrix.num_cols)


def select_rows(matrix: CSR, rows: Tensor) -> CSR:
    """The ``(len(rows), num_cols)`` CSR made of the given ``(R,)`` int64 rows, in that order."""
    counts = matrix.crow.diff()[rows]
    crow = _pointers(counts)
    source_start = torch.repeat_interleave(matrix.crow[rows] - crow[:-1], counts)
    index = torch.arange(int(crow[-1]), device=rows.device) + source_start
    return CSR(crow, matrix.col[index], matrix.val[index], matrix.num_cols)


def slice_rows(matrix: CSR, start: int, stop: int) -> CSR:
    """Rows ``[start, stop)`` of a CSR as a ``(stop - start, num_cols)`` CSR."""
    lo, hi = int(matrix.crow[start]), int(matrix.crow[stop])
    return CSR(
        matrix.crow[start : stop + 1] - lo, matrix.col[lo:hi], matrix.val[lo:hi], matrix.num_cols
    )


def symmetric_csr(edges: Tensor, edge_values: Tensor, diagonal: Tensor) -> CSR:
    """``(V, V)`` CSR with ``edge_values`` at ``(i, j)`` and ``(j, i)`` of each ``(E, 2)`` edge
    and ``diagonal`` ``(V,)`` on the diagonal, columns sorted within each row."""
    num_vertices = diagonal.shape[0]
    arange = torch.arange(num_vertices, device=edges.device)
    rows = torch.cat([edges[:, 0], edges[:, 1], arange])
    cols = torch.cat([edges[:, 1], edges[:, 0], arange])
    vals = torch.cat([edge_values, edge_values, diagonal])
    order = torch.argsort(rows * num_vertices + cols)
    rows, cols, vals = rows[order], cols[order], vals[order]
    return CSR(compress_rows(rows, num_vertices), cols, vals, num_vertices)


def work_blocks(work_per_row: Tensor, budget: int) -> list[tuple[int, int]]:
    """Split ``(n,)`` items (rows, or stored entries) into contiguous ``[start, stop)`` blocks
    of at most ``budget`` work each; a single item heavier than the budget forms a block of its
    own."""
    num_rows = int(work_per_row.shape[0])
    cumulative = torch.cumsum(work_per_row, dim=0).cpu()
    blocks, start, done = [], 0, 0
    while start < num_rows:
        stop = max(int(torch.searchsorted(cumulative, done + budget, right=True)), start + 1)
        blocks.append((start, stop))
        done = int(cumulative[stop - 1])
        start = stop
    return blocks


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

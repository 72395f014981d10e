"""Row storage the kernels read and write: ``Lhat`` split off its diagonal, the rows of
``F^(1)``, and CSR rows with gaps (:class:`Rows`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .block import SplitLhat
from .jit import kernel_jit
from .threads import numba_available

if numba_available():
    from .block import _first_row

if numba_available():

    @kernel_jit(nogil=True)
    def _split_diagonal(l_crow, l_col, l_val, index_like):
        """``Lhat = diag(d) + W``: ``(d, w_crow, w_col, w_val, row_sums)``, ``W`` without the
        diagonal (columns in the dtype of ``index_like``) and ``row_sums`` those of ``Lhat``
        (summed in row order)."""
        num_rows = l_crow.shape[0] - 1
        diagonal = np.zeros(num_rows, dtype=l_val.dtype)
        row_sums = np.zeros(num_rows, dtype=l_val.dtype)
        w_crow = np.zeros(num_rows + 1, dtype=np.int64)
        for i in range(num_rows):
            off_diagonal = 0
            for slot in range(l_crow[i], l_crow[i + 1]):
                off_diagonal += l_col[slot] != i
            w_crow[i + 1] = off_diagonal
        for i in range(num_rows):
            w_crow[i + 1] += w_crow[i]
        w_col = np.empty(w_crow[-1], dtype=index_like.dtype)
        w_val = np.empty(w_crow[-1], dtype=l_val.dtype)
        for i in range(num_rows):
            count = w_crow[i]
            for slot in range(l_crow[i], l_crow[i + 1]):
                row_sums[i] += l_val[slot]
                if l_col[slot] == i:
                    diagonal[i] += l_val[slot]
                else:
                    w_col[count] = l_col[slot]
                    w_val[count] = l_val[slot]
                    count += 1
        return diagonal, w_crow, w_col, w_val, row_sums

    @kernel_jit(nogil=True)
    def _packed_first_rows(lhat, rows, out_col):
        """Rows ``rows`` of ``F^(1)`` (each as :func:`_first_row` gives it), packed:
        ``(out_crow, out_val)``, the columns written to ``out_col`` (in their index dtype)."""
        out_crow = np.zeros(rows.shape[0] + 1, dtype=np.int64)
        for r in range(rows.shape[0]):
            out_crow[r + 1] = out_crow[r] + lhat.w_crow[rows[r] + 1] - lhat.w_crow[rows[r]] + 1
        out_val = np.empty(out_crow[-1], dtype=lhat.w_val.dtype)
        for r in range(rows.shape[0]):
            start = out_crow[r]
            _first_row(rows[r], lhat, out_col[start:], out_val[start:])
        return out_crow, out_val

    @kernel_jit(nogil=True)
    def _gather_rows(starts, counts, col, val, crow, out_col, out_val):
        """Copy the rows of a gapped CSR back to back at ``crow`` (a packed CSR)."""
        for i in range(starts.shape[0]):
            source, size = starts[i], counts[i]
            out_col[crow[i] : crow[i] + size] = col[source : source + size]
            out_val[crow[i] : crow[i] + size] = val[source : source + size]

    @kernel_jit(nogil=True)
    def _products(f_start, f_count, f_col, w_crow):
        """See :func:`step_costs`."""
        products = np.zeros(f_start.shape[0], dtype=np.int64)
        for i in range(f_start.shape[0]):
            total = 0
            for e in range(f_start[i], f_start[i] + f_count[i]):
                total += w_crow[f_col[e] + 1] - w_crow[f_col[e]] + 1
            products[i] = total
        return products


def split_lhat(crow: np.ndarray, col: np.ndarray, val: np.ndarray, index=None) -> SplitLhat:
    """Split ``Lhat`` given in CSR form (every row holds its diagonal entry); ``W``'s columns
    in the dtype ``index`` (default: that of ``col``)."""
    index_like = np.empty(0, dtype=col.dtype if index is None else index)
    return SplitLhat(*_split_diagonal(crow, col, val, index_like))


def first_rows(lhat: SplitLhat, rows: np.ndarray | None = None, index=np.int64) -> Rows:
    """Rows ``rows`` (``(R,)`` int64, in that order; default all) of ``F^(1)``, the split
    ``lhat`` normalised by rows, packed with ``index`` column indices."""
    if rows is None:
        rows = np.arange(lhat.num_cols, dtype=np.int64)
    size = int((lhat.w_crow[rows + 1] - lhat.w_crow[rows]).sum()) + rows.shape[0]
    out_col = np.empty(size, dtype=index)
    out_crow, out_val = _packed_first_rows(lhat, rows, out_col)
    return Rows.from_csr(out_crow, out_col, out_val)


@dataclass
class Rows:
    """A CSR matrix whose rows may be separated by unused entries: row ``i`` is
    ``col[starts[i] : starts[i] + counts[i]]`` (and the same slice of ``val``), ``starts`` and
    ``counts`` ``(n,)`` int64, ``col`` ``(capacity,)`` int32 or int64, ``val`` ``(capacity,)``
    float; ``costs``: ``(n,)`` int64 scalar products each row costs in the next step, or
    ``None``."""

    starts: np.ndarray
    counts: np.ndarray
    col: np.ndarray
    val: np.ndarray
    costs: np.ndarray | None = None

    @classmethod
    def from_csr(cls, crow: np.ndarray, col: np.ndarray, val: np.ndarray) -> Rows:
        """View a packed CSR ``(crow, col, val)``."""
        return cls(crow[:-1], np.diff(crow), col, val)

    @property
    def num_rows(self) -> int:
        return int(self.starts.shape[0])

    @property
    def nnz(self) -> int:
        return int(self.counts.sum())

    def to_csr(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(crow, col, val)``: the rows packed into fresh arrays."""
        crow = np.zeros(self.num_rows + 1, dtype=np.int64)
        np.cumsum(self.counts, out=crow[1:])
        col = np.empty(crow[-1], dtype=self.col.dtype)
        val = np.empty(crow[-1], dtype=self.val.dtype)
        _gather_rows(self.starts, self.counts, self.col, self.val, crow, col, val)
        return crow, col, val


def step_costs(rows: Rows, lhat: SplitLhat) -> np.ndarray:
    """``(n,)`` int64 scalar products each row of ``rows @ Lhat`` costs (``W`` and diagonal)."""
    if rows.costs is not None:
        return rows.costs
    return _products(rows.starts, rows.counts, rows.col, lhat.w_crow)


def index_dtype(num_cols: int) -> type:
    """``np.int32`` when it can index ``num_cols`` columns (the steps read and write every
    stored column index: 4 bytes save memory and traffic), else ``np.int64``."""
    return np.int32 if num_cols <= np.iinfo(np.int32).max else np.int64

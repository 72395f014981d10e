"""Sparse CSR matrices: the container, the registered ``stochlap::`` torch operators and the
differentiable pattern operations.

The operators take CSR components as ordinary tensors (torch's fake-tensor machinery does not
accept ``torch.sparse_csr`` inputs); :class:`CSR` converts at the public boundary.
"""

from .autograd import pattern_matmul
from .csr import (
    CSR,
    compress_rows,
    constant_matmul,
    permute_csr,
    row_ids,
    select_rows,
    slice_rows,
    symmetric_csr,
    work_blocks,
)
from .ops import (
    csr_matmul,
    normalize_rows,
    row_abs_diff_sum,
    scale_columns,
    spmm,
    threshold_rows,
)

__all__ = [
    "CSR",
    "compress_rows",
    "constant_matmul",
    "csr_matmul",
    "normalize_rows",
    "pattern_matmul",
    "permute_csr",
    "row_abs_diff_sum",
    "row_ids",
    "scale_columns",
    "select_rows",
    "slice_rows",
    "spmm",
    "symmetric_csr",
    "threshold_rows",
    "work_blocks",
]

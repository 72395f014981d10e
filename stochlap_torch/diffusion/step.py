"""One diffusion step of Algorithm 1, the single definition every run goes through.

One step, for ``k = 2..K``::

    G     = [F^(k-1) Lhat]_r          (product, row normalisation)
    G     = G with entries < lambda set to 0 (a row's largest entry is always kept)
    F^(k) = [alpha ∘ G]_r             (Schur product with alpha on every row)

with, in the same pass, ``D^(k)(i) = sum_j |F^(k) - F^(k-1)|(i, j)`` (Algorithm 2) and
``F^(k) P``, by the ``stochlap::diffusion_step`` operator (the numba kernel on the CPU).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .. import _kernels, sparse
from ..operators import MeshOperators
from ..sparse import CSR, spmm
from ..sparse.ops import dynamic_csr_like
from ..sparse.registry import define_op


def kernel_lhat(ops: MeshOperators) -> tuple[_kernels.SplitLhat, np.ndarray]:
    """``Lhat`` split for the numba kernel (columns in ``_kernels.index_dtype``: one compiled
    specialisation serves every path) and ``alpha`` in its dtype."""
    arrays = (ops.lhat.crow.numpy(), ops.lhat.col.numpy(), ops.lhat.val.numpy())
    lhat = _kernels.split_lhat(*arrays, _kernels.index_dtype(ops.num_vertices))
    return lhat, ops.alpha.numpy().astype(lhat.diagonal.dtype, copy=False)


def _fused_step_fake(
    f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points, sort_columns=True
):
    return (
        *dynamic_csr_like(f_crow, f_col, f_val),
        f_val.new_empty(f_crow.shape[0] - 1),
        points.new_empty(points.shape),
    )


def _fused_step_cpu(
    f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points, sort_columns=True
):
    """The CPU kernel of ``stochlap::diffusion_step``: the numba kernel when available."""
    if not _kernels.numba_available():
        return _torch_step(f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points)
    dtype = f_val.numpy().dtype
    lhat = _kernels.split_lhat(l_crow.numpy(), l_col.numpy(), l_val.numpy())
    num_cols = int(l_crow.shape[0]) - 1
    with _kernels.WORKSPACES.borrow(num_cols, dtype, 0, f_col.numpy().dtype) as workspace:
        rows, difference, moved = _kernels.fused_step(
            _kernels.Rows.from_csr(f_crow.numpy(), f_col.numpy(), f_val.numpy()),
            lhat,
            alpha.numpy().astype(dtype, copy=False),
            float(threshold),
            points.numpy().astype(dtype, copy=False),
            torch.get_num_threads(),
            sort_columns,
            workspace,
        )
        packed = rows.to_csr()
    return (
        *(torch.from_numpy(a) for a in packed),
        torch.from_numpy(difference),
        torch.from_numpy(moved),
    )


@define_op(
    "diffusion_step(Tensor f_crow, Tensor f_col, Tensor f_val, Tensor l_crow, Tensor l_col, "
    "Tensor l_val, Tensor alpha, float threshold, Tensor points, bool sort_columns=True) "
    "-> (Tensor, Tensor, Tensor, Tensor, Tensor)",
    fake=_fused_step_fake,
    cpu=_fused_step_cpu,
)
def _torch_step(
    f_crow, f_col, f_val, l_crow, l_col, l_val, alpha, threshold, points, sort_columns=True
):
    """``stochlap::diffusion_step``: ``F^(k)`` as ``(crow, col, val)``, ``D^(k)`` ``(V,)`` and
    ``F^(k) P``, composed from the separate ``stochlap`` ops (always sorted; the CPU kernel
    leaves a row's columns in any order with ``sort_columns=False``)."""
    previous = CSR(f_crow, f_col, f_val, int(l_crow.shape[0]) - 1)
    lhat = CSR(l_crow, l_col, l_val, previous.num_cols)
    product = sparse.normalize_rows(sparse.csr_matmul(previous, lhat))
    kept = sparse.threshold_rows(product, threshold)
    following = sparse.normalize_rows(sparse.scale_columns(kept, alpha.to(kept.val.dtype)))
    difference = sparse.row_abs_diff_sum(following, previous)
    return following.crow, following.col, following.val, difference, spmm(following, points)


class ConstantOperatorStep:
    """``step(F^(k-1)) -> (F^(k), D^(k), F^(k) P)`` with the operators constant: when
    ``points`` carries gradients, ``F^(k) P`` is recomputed with :func:`~.sparse.spmm`.

    Args:
        ops: the operators.
        threshold: ``lambda``.
        points: ``(V, C)`` positions (``C`` may be 0 when only the operators are wanted).
        backend: ``"numba"`` (``stochlap::diffusion_step``) or ``"torch"`` (the composed ops).
        sort_columns: keep the columns of every ``F^(k)`` sorted (when they are returned).
    """

    def __init__(
        self,
        ops: MeshOperators,
        threshold: float,
        points: Tensor,
        backend: str,
        sort_columns: bool = True,
    ):
        self.ops, self.threshold, self.points = ops, float(threshold), points
        self.backend, self.sort_columns = backend, sort_columns
        self.track = points.requires_grad and torch.is_grad_enabled()

    def __call__(self, previous: CSR) -> tuple[CSR, Tensor, Tensor]:
        f, lhat, alpha = previous, self.ops.lhat, self.ops.alpha
        step = torch.ops.stochlap.diffusion_step if self.backend == "numba" else _torch_step
        with torch.no_grad():
            args = (f.crow, f.col, f.val, lhat.crow, lhat.col, lhat.val, alpha, self.threshold)
            crow, col, val, difference, moved = step(*args, self.points.detach(), self.sort_columns)
        following = CSR(crow, col, val, f.num_cols)
        if self.track:
            moved = spmm(following, self.points)
        return following, difference, moved


def scale_steps(first: CSR, step, num_scales: int):
    """The loop over scales: ``(k, F^(k), D^(k), F^(k) P)`` for ``k = 2..K`` from ``F^(1)``;
    ``step`` is a :class:`ConstantOperatorStep` or the differentiable step of :mod:`.autodiff`."""
    current = first
    for k in range(2, num_scales + 1):
        current, difference, moved = step(current)
        yield k, current, difference, moved

"""Gradients through the operators: ``F^(k)`` as a function of the vertex positions.

The default path (:func:`~stochlap_torch.diffusion.multiscale_representation`) holds the
operators constant and differentiates only ``P^(k) = F^(k) P``. Here the edge weights
``1 / |Pi - Pj|^2`` and ``alpha`` (Eq. 9) are differentiable too, and every step::

    Q     = F^(k-1) Lhat                  (full product pattern)
    G     = Q / rowsum(Q)                 (normalised)
    G     = G on the entries kept by the threshold at the forward pass (pattern fixed)
    F^(k) = rownorm(alpha[col] * G)

is built from torch gathers and ``index_add`` on fixed sparsity patterns. The product has its
own :class:`torch.autograd.Function` that saves only the two operands and recomputes the
expansion (one term per pair of stored entries) in bounded row blocks in the backward pass, so
autograd keeps ``O(nnz)`` per scale, ``O(K nnz)`` in all, and never forms a dense ``V x V``
matrix or uses torch's sparse autograd.

The threshold pattern is a piecewise-constant function of the positions: it is fixed at the
forward pass and the gradient is that of the smooth map on the current pattern.
"""

from __future__ import annotations

import torch
from torch import Tensor

from .batch import check_batch
from .diffusion import MultiscaleRepresentation, check_parameters
from .mesh import as_mesh_tensors
from .operators import abs_laplacian, alpha_from_edges, unique_edges
from .sparse_ops import CSR, csr_matmul, row_ids, spmm, threshold_rows

__all__ = ["EXPANSION_BLOCK", "differentiable_multiscale", "pattern_matmul"]

#: Upper bound on the product terms one block of :func:`pattern_matmul` expands at once.
EXPANSION_BLOCK = 1 << 22


def _entry_blocks(counts: Tensor, budget: int) -> list[tuple[int, int]]:
    """Split entries into ``[start, stop)`` ranges of at most ``budget`` expanded terms."""
    cumulative = torch.cumsum(counts, dim=0).cpu()
    total = int(cumulative[-1]) if cumulative.numel() else 0
    blocks, start, done = [], 0, 0
    while start < counts.shape[0] and done < total:
        stop = max(int(torch.searchsorted(cumulative, done + budget, right=True)), start + 1)
        blocks.append((start, stop))
        done, start = int(cumulative[stop - 1]), stop
    return blocks


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


def _csr_keys(matrix: CSR) -> Tensor:
    """``(nnz,)`` sorted ``row * num_cols + col`` keys of a row-major CSR with sorted columns."""
    return row_ids(matrix.crow, matrix.nnz) * matrix.num_cols + matrix.col


class _PatternMatmul(torch.autograd.Function):
    """Values of ``a @ b`` on a given pattern; saves operands, recomputes terms per block."""

    @staticmethod
    def forward(ctx, a_val, b_val, a_crow, a_col, b_crow, b_col, c_keys, num_cols):
        a = CSR(a_crow, a_col, a_val, int(b_crow.shape[0]) - 1)
        b = CSR(b_crow, b_col, b_val, num_cols)
        out = a_val.new_zeros(c_keys.shape[0])
        for start, stop in _entry_blocks(b_crow[a_col + 1] - b_crow[a_col], EXPANSION_BLOCK):
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
        for start, stop in _entry_blocks(b_crow[a_col + 1] - b_crow[a_col], EXPANSION_BLOCK):
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
        a.val, b.val, a.crow, a.col, b.crow, b.col, _csr_keys(pattern), b.num_cols
    )


def _row_normalise(crow: Tensor, val: Tensor) -> Tensor:
    """Differentiable ``[.]_r``: each row of a CSR divided by its sum."""
    rows = row_ids(crow, val.shape[0])
    sums = val.new_zeros(crow.shape[0] - 1).index_add(0, rows, val)
    return val / sums[rows]


def _row_abs_diff(a: CSR, b: CSR) -> Tensor:
    """Differentiable ``(V,)`` ``sum_j |a - b|(i, j)`` over the union of the two patterns."""
    keys = torch.cat([_csr_keys(a), _csr_keys(b)])
    unique, inverse = torch.unique(keys, sorted=True, return_inverse=True)
    values = torch.cat([a.val, -b.val])
    difference = values.new_zeros(unique.shape[0]).index_add(0, inverse, values)
    rows = torch.div(unique, a.num_cols, rounding_mode="floor")
    return values.new_zeros(a.num_rows).index_add(0, rows, difference.abs())


def _kept_entries(product: CSR, kept: CSR) -> Tensor:
    """``(nnz_kept,)`` positions in ``product`` of the entries of ``kept`` (a sub-pattern)."""
    return torch.searchsorted(_csr_keys(product), _csr_keys(kept))


def _step(previous: CSR, lhat: CSR, alpha: Tensor, threshold: float) -> CSR:
    """``F^(k)`` from ``F^(k-1)`` with differentiable values on a pattern fixed now."""
    with torch.no_grad():
        pattern = csr_matmul(
            CSR(previous.crow, previous.col, previous.val.detach(), previous.num_cols),
            CSR(lhat.crow, lhat.col, lhat.val.detach(), lhat.num_cols),
        )
    product_val = pattern_matmul(previous, lhat, pattern)
    normalised = _row_normalise(pattern.crow, product_val)
    with torch.no_grad():
        kept = threshold_rows(pattern.with_values(normalised.detach()), threshold)
        positions = _kept_entries(pattern, kept)
    scaled = normalised[positions] * alpha[kept.col]
    return CSR(kept.crow, kept.col, _row_normalise(kept.crow, scaled), kept.num_cols)


def differentiable_multiscale(
    vertices: Tensor,
    faces: Tensor,
    num_scales: int = 8,
    threshold: float = 1e-3,
    batch: Tensor | None = None,
    return_operators: bool = False,
) -> MultiscaleRepresentation:
    """Algorithm 1 with gradients through ``P``, the edge weights and ``alpha`` into ``F^(k)``.

    Forward values equal :func:`~stochlap_torch.diffusion.multiscale_representation` (to
    rounding). ``positions``, ``coefficients`` and ``differences`` are differentiable w.r.t.
    ``vertices``; the thresholded sparsity pattern of each ``F^(k)`` is fixed at the forward
    pass. Saved memory is ``O(K nnz)``.

    Args:
        vertices: ``(V, 3)`` float tensor (float64 recommended for gradient checks).
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        batch: optional ``(V,)`` int64 mesh index of every vertex of a packed batch.
        return_operators: also return ``F^(1..K)`` as ``torch.sparse_csr`` tensors (values
            detached).

    Raises:
        MeshError: bad input mesh.
        ValueError: bad ``num_scales`` or ``threshold``.
    """
    check_parameters(num_scales, threshold)
    if not isinstance(vertices, Tensor) or not vertices.is_floating_point():
        found = getattr(vertices, "dtype", type(vertices).__name__)
        raise TypeError(f"vertices must be a floating-point torch.Tensor, got {found}")
    _, faces = as_mesh_tensors(vertices.detach(), faces)  # validation only
    points = vertices
    if batch is not None:
        batch = check_batch(batch.to(points.device), points.shape[0], faces)
    edges = unique_edges(faces, points.shape[0])
    lhat = abs_laplacian(points, edges)
    alpha = alpha_from_edges(points, edges, batch)
    current = lhat.with_values(_row_normalise(lhat.crow, lhat.val))
    positions = [points]
    differences = [points.new_zeros(points.shape[0])]
    entries = [current.nnz]
    operators = [current] if return_operators else None
    for _ in range(2, num_scales + 1):
        following = _step(current, lhat, alpha, threshold)
        differences.append(_row_abs_diff(following, current))
        positions.append(spmm(following, points))
        entries.append(following.nnz)
        if operators is not None:
            operators.append(following)
        current = following
    stacked = torch.stack(positions)
    returned = None
    if return_operators:
        returned = [op.with_values(op.val.detach()).to_sparse_csr() for op in operators]
    return MultiscaleRepresentation(
        positions=stacked,
        differences=torch.stack(differences),
        entries=torch.tensor(entries, dtype=torch.int64),
        operators=returned,
        batch=batch,
    )

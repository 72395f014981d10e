"""Gradients through the operators: ``F^(k)`` as a function of the vertex positions.

The default path (:func:`~stochlap_torch.diffusion.multiscale_representation`) holds the
operators constant and differentiates only ``P^(k) = F^(k) P``. Here the edge weights
``1 / |Pi - Pj|^2`` and ``alpha`` (Eq. 9) are differentiable too, and every step::

    Q     = F^(k-1) Lhat                  (full product pattern)
    G     = Q / rowsum(Q)                 (normalised)
    G     = G on the entries kept by the threshold at the forward pass (pattern fixed)
    F^(k) = rownorm(alpha[col] * G)

is built from torch gathers and ``index_add`` on fixed sparsity patterns
(:mod:`stochlap_torch.sparse.autograd`): ``O(K nnz)`` in all. The threshold's pattern is
fixed at the forward pass: the gradient is that of the smooth map on that pattern.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..mesh import as_mesh_tensors, check_batch, extent_scale, unique_edges
from ..operators import MeshOperators, abs_laplacian, alpha_from_edges
from ..params import PaperParams
from ..sparse import CSR, csr_matmul, pattern_matmul, spmm, threshold_rows
from ..sparse.autograd import kept_entries, row_abs_diff, row_normalise
from .engine import run_steps
from .parameters import check_parameters
from .representation import MultiscaleRepresentation


class DifferentiableStep:
    """``step(F^(k-1)) -> (F^(k), D^(k), F^(k) P)`` with gradients to the ``(V, 3)``
    ``points`` through ``lhat`` (``Lhat``), the ``(V,)`` ``alpha`` and ``points`` themselves."""

    def __init__(self, lhat: CSR, alpha: Tensor, threshold: float, points: Tensor):
        self.lhat, self.alpha, self.threshold, self.points = lhat, alpha, threshold, points

    def __call__(self, previous: CSR) -> tuple[CSR, Tensor, Tensor]:
        lhat = self.lhat
        with torch.no_grad():
            pattern = csr_matmul(
                CSR(previous.crow, previous.col, previous.val.detach(), previous.num_cols),
                CSR(lhat.crow, lhat.col, lhat.val.detach(), lhat.num_cols),
            )
        normalised = row_normalise(pattern.crow, pattern_matmul(previous, lhat, pattern))
        with torch.no_grad():
            kept = threshold_rows(pattern.with_values(normalised.detach()), self.threshold)
            positions = kept_entries(pattern, kept)
        scaled = normalised[positions] * self.alpha[kept.col]
        following = CSR(kept.crow, kept.col, row_normalise(kept.crow, scaled), kept.num_cols)
        return following, row_abs_diff(following, previous), spmm(following, self.points)


def differentiable_multiscale(
    vertices: Tensor,
    faces: Tensor,
    num_scales: int = PaperParams.num_scales,
    threshold: float = PaperParams.threshold,
    batch: Tensor | None = None,
    return_operators: bool = False,
    max_memory: int | None = None,
) -> MultiscaleRepresentation:
    """Algorithm 1 with gradients through ``P``, the edge weights and ``alpha`` into ``F^(k)``:
    the values of :func:`~stochlap_torch.diffusion.multiscale_representation` (to rounding),
    ``positions``, ``coefficients`` and ``differences`` differentiable w.r.t. ``vertices``.

    Args:
        vertices: ``(V, 3)`` float tensor (float64 recommended for gradient checks).
        faces, num_scales, threshold, batch: as for
            :func:`~stochlap_torch.diffusion.multiscale_representation`.
        return_operators: also return ``F^(1..K)`` as ``torch.sparse_csr`` tensors (values
            detached).
        max_memory: byte budget for the operators the graph keeps (default:
            ``$STOCHLAP_MAX_MEMORY``, else half the physical memory).

    Raises:
        MeshError: bad input mesh.
        ValueError: bad ``num_scales`` or ``threshold``.
        MemoryBudgetError: the operators would not fit the budget.
    """
    num_scales, threshold = check_parameters(num_scales, threshold)
    if not isinstance(vertices, Tensor) or not vertices.is_floating_point():
        found = getattr(vertices, "dtype", type(vertices).__name__)
        raise TypeError(f"vertices must be a floating-point torch.Tensor, got {found}")
    _, faces = as_mesh_tensors(vertices.detach(), faces)  # validation only
    # A power-of-two scale keeps squared lengths finite (exact; see extent_scale).
    scale = extent_scale(vertices.detach())
    points = vertices if scale == 1.0 else vertices * scale
    if batch is not None:
        batch = check_batch(batch, points.shape[0], faces)
    edges = unique_edges(faces, points.shape[0])
    lhat = abs_laplacian(points, edges)
    alpha = alpha_from_edges(points, edges, batch)
    first = lhat.with_values(row_normalise(lhat.crow, lhat.val))
    with torch.no_grad():  # the memory check and the sample step hold constant operators
        ops = MeshOperators(lhat.with_values(lhat.val.detach()), alpha.detach())
    step = DifferentiableStep(lhat, alpha, threshold, points)
    options = {"keep_operators": return_operators, "max_memory": max_memory}
    steps = run_steps(
        ops, points, num_scales, threshold, backend="torch", step=step, first=first, **options
    )
    return steps.representation(scale, batch)

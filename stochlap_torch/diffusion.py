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
import math
import os
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from .operators import MeshOperators, mesh_operators
from .sparse_ops import (
    CSR,
    csr_matmul,
    normalize_rows,
    row_abs_diff_sum,
    scale_columns,
    spmm,
    threshold_rows,
)

__all__ = [
    "MemoryBudgetError",
    "MultiscaleRepresentation",
    "check_parameters",
    "diffusion_step",
    "estimate_memory",
    "multiscale_representation",
]

logger = logging.getLogger(__name__)

#: Bytes one stored entry of ``F`` costs (int64 column + float64 value).
_BYTES_PER_ENTRY = 16
#: Environment variable that overrides the default memory budget, in bytes.
MEMORY_ENV = "STOCHLAP_MAX_MEMORY"

ProgressCallback = Callable[[int, int], None]


class MemoryBudgetError(MemoryError):
    """The operators would exceed the memory budget (usually: threshold too close to 0)."""


@dataclass
class MultiscaleRepresentation:
    """The multiscale representation of one mesh (Algorithm 1), scales ``k = 1..K``.

    Attributes:
        positions: ``(K, V, 3)``; ``positions[0]`` is the input ``P``, ``positions[k-1]`` is
            ``P^(k) = F^(k) P``.
        coefficients: ``(K, V, 3)``; ``coefficients[0] = 0``,
            ``coefficients[k-1] = positions[k-2] - positions[k-1]`` (``C^(k)``).
        differences: ``(K, V)``; ``differences[0] = 0``, ``differences[k-1]`` is the difference
            map ``D^(k)(i) = sum_j |F^(k)(i, j) - F^(k-1)(i, j)|`` of Algorithm 2.
        operators: the ``K`` matrices ``F^(1..K)`` as ``(V, V)`` ``torch.sparse_csr`` tensors
            (``F^(1)`` is the stochastic mesh Laplacian), or ``None`` when not requested.
    """

    positions: Tensor
    coefficients: Tensor
    differences: Tensor
    operators: list[Tensor] | None = None

    @property
    def num_scales(self) -> int:
        return int(self.positions.shape[0])

    def reconstruct(self) -> Tensor:
        """``(V, 3)`` input positions from the coarsest scale and all coefficients (Eq. 22)."""
        return self.positions[-1] + self.coefficients.sum(dim=0)

    def saliency(self) -> Tensor:
        """``(V,)`` saliency of Algorithm 2, ``log(sum_k D^(k))``."""
        from .saliency_map import saliency_from_differences  # it builds on this module

        return saliency_from_differences(self.differences)


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


def estimate_memory(
    num_vertices: int,
    num_edges: int,
    num_scales: int,
    threshold: float,
    return_operators: bool = False,
) -> int:
    """Estimated peak bytes of the sparse operators for ``K = num_scales``.

    A row of ``F^(k)`` is supported on the ``k``-ring of its vertex (about
    ``1 + d k (k + 1) / 2`` vertices for mean valence ``d``), and after thresholding holds at
    most ``1 / threshold`` entries (they are ``>= threshold`` and sum to at most 1), and never
    more than ``V``.
    """
    valence = 2.0 * num_edges / max(num_vertices, 1)
    ring = 1.0 + valence * num_scales * (num_scales + 1) / 2.0
    per_row = min(float(num_vertices), ring, math.floor(1.0 / threshold) + valence + 1)
    held = num_scales if return_operators else 2
    return int(num_vertices * per_row * _BYTES_PER_ENTRY * (held + 1))


def diffusion_step(previous: CSR, ops: MeshOperators, threshold: float) -> CSR:
    """``F^(k)`` from ``F^(k-1)``: ``[alpha ∘ T_lambda([F^(k-1) Lhat]_r)]_r``."""
    product = normalize_rows(csr_matmul(previous, ops.lhat))
    kept = threshold_rows(product, threshold)
    return normalize_rows(scale_columns(kept, ops.alpha.to(kept.val.dtype)))


def multiscale_representation(
    vertices,
    faces,
    num_scales: int = 8,
    threshold: float = 1e-3,
    return_operators: bool = False,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
) -> MultiscaleRepresentation:
    """Multiscale representation of a mesh (Algorithm 1) with the difference maps of Alg. 2.

    Args:
        vertices: ``(V, 3)`` float tensor; its dtype and device are kept throughout. Gradients
            flow into ``positions`` through ``P^(k) = F^(k) P`` with the operators held
            constant.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``; entries of the normalised product below it are
            dropped at every step.
        return_operators: keep all ``F^(k)`` (costs ``K`` times the memory of one).
        max_memory: byte budget for the operators; defaults to :func:`default_memory_budget`.
        progress: called as ``progress(k, K)`` after each scale.

    Raises:
        MeshError: bad input mesh.
        ValueError: bad ``num_scales`` or ``threshold``.
        MemoryBudgetError: the operators would not fit the budget.
    """
    check_parameters(num_scales, threshold)
    with torch.no_grad():
        ops = mesh_operators(vertices.detach() if isinstance(vertices, Tensor) else vertices, faces)
    points = vertices if isinstance(vertices, Tensor) else torch.as_tensor(vertices)
    points = points.to(ops.alpha.dtype) if not points.is_floating_point() else points
    budget = default_memory_budget() if max_memory is None else int(max_memory)
    estimate = estimate_memory(
        ops.num_vertices, ops.edges.shape[0], num_scales, threshold, return_operators
    )
    if estimate > budget:
        raise MemoryBudgetError(
            f"the operators for {ops.num_vertices} vertices at num_scales={num_scales}, "
            f"threshold={threshold:g} would need about {estimate / 2**30:.1f} GiB, over the "
            f"budget of {budget / 2**30:.1f} GiB. Raise the threshold, lower num_scales, or "
            f"raise the budget (max_memory=..., or ${MEMORY_ENV})."
        )

    current = ops.stochastic_laplacian()
    positions, differences = [points], [points.new_zeros(ops.num_vertices)]
    operators = [current] if return_operators else None
    if progress is not None:
        progress(1, num_scales)
    for k in range(2, num_scales + 1):
        with torch.no_grad():
            following = diffusion_step(current, ops, threshold)
            differences.append(row_abs_diff_sum(following, current))
        positions.append(spmm(following, points))
        if operators is not None:
            operators.append(following)
        logger.debug(
            "scale %d/%d: %.1f entries per row", k, num_scales, following.nnz / ops.num_vertices
        )
        current = following
        if progress is not None:
            progress(k, num_scales)

    stacked = torch.stack(positions)
    coefficients = torch.cat([torch.zeros_like(stacked[:1]), stacked[:-1] - stacked[1:]])
    return MultiscaleRepresentation(
        positions=stacked,
        coefficients=coefficients,
        differences=torch.stack(differences),
        operators=None if operators is None else [op.to_sparse_csr() for op in operators],
    )

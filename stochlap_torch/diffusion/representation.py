"""What a run of the steps returns: the multiscale representation of Algorithm 1, and the
saliency of Algorithm 2 that reduces its difference maps."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import torch
from torch import Tensor


@dataclass
class MultiscaleRepresentation:
    """The multiscale representation of one mesh (Algorithm 1), scales ``k = 1..K``.

    Attributes:
        positions: ``(K, V, 3)``; ``positions[0]`` is the input ``P``, ``positions[k-1]`` is
            ``P^(k) = F^(k) P``.
        coefficients: ``(K, V, 3)``; ``coefficients[0] = 0``,
            ``coefficients[k-1] = positions[k-2] - positions[k-1]`` (``C^(k)``), computed on
            first access (:func:`scale_coefficients`).
        differences: ``(K, V)``; ``differences[0] = 0``, ``differences[k-1]`` is the difference
            map ``D^(k)(i) = sum_j |F^(k)(i, j) - F^(k-1)(i, j)|`` of Algorithm 2.
        entries: ``(K,)`` int64 number of stored entries of each ``F^(k)``.
        operators: the ``K`` matrices ``F^(1..K)`` as ``(V, V)`` ``torch.sparse_csr`` tensors
            (``F^(1)`` is the stochastic mesh Laplacian; block diagonal for a batch), or
            ``None`` when not requested.
        batch: the ``(V,)`` mesh index of every vertex for a packed batch, else ``None``.
    """

    positions: Tensor
    differences: Tensor
    entries: Tensor
    operators: list[Tensor] | None = None
    batch: Tensor | None = None

    @property
    def num_scales(self) -> int:
        return int(self.positions.shape[0])

    @cached_property
    def coefficients(self) -> Tensor:
        """``(K, V, 3)`` ``C^(k)``, computed once (with a graph when ``positions`` carry
        gradients and grad mode is on at that first access)."""
        return scale_coefficients(self.positions)

    def reconstruct(self) -> Tensor:
        """``(V, 3)`` input positions from the coarsest scale and all coefficients (Eq. 22)."""
        return self.positions[-1] + self.coefficients.sum(dim=0)

    def saliency(self) -> Tensor:
        """``(V,)`` saliency of Algorithm 2, ``log(sum_k D^(k))``
        (:func:`saliency_from_differences`)."""
        return saliency_from_differences(self.differences, self.batch)


def scale_coefficients(positions: Tensor) -> Tensor:
    """``(K, V, C)`` coefficients ``C^(k) = P^(k-1) - P^(k)`` of ``(K, V, C)`` positions
    (Eq. 16), ``C^(1) = 0``; differentiable when ``positions`` carries gradients."""
    if positions.requires_grad and torch.is_grad_enabled():
        return torch.cat([torch.zeros_like(positions[:1]), positions[:-1] - positions[1:]])
    out = torch.empty_like(positions)  # one pass, no temporary
    out[0] = 0
    torch.sub(positions[:-1], positions[1:], out=out[1:])
    return out


def saliency_from_differences(differences: Tensor, batch: Tensor | None = None) -> Tensor:
    """``I = log(sum_{k=2..K} D^(k))`` with a finite value where the sum is zero.

    Args:
        differences: ``(K, V)`` difference maps, ``differences[0] = 0``.
        batch: optional ``(V,)`` int64 mesh index of every vertex, for packed batches
            (``None``: one mesh).

    Returns:
        ``(V,)`` saliency. A vertex whose difference maps are all zero (no edges) gets the
        smallest saliency of the other vertices of its mesh, or ``0`` if there are none.
    """
    total = differences.sum(dim=0)
    defined = total > 0
    saliency = torch.log(torch.where(defined, total, torch.ones_like(total)))
    if bool(defined.all()):
        return saliency
    if batch is None:
        batch = torch.zeros_like(total, dtype=torch.int64)
    num_meshes = int(batch.max()) + 1
    lowest = saliency.new_full((num_meshes,), torch.inf).scatter_reduce_(
        0, batch[defined], saliency[defined], reduce="amin"
    )
    lowest = torch.where(torch.isfinite(lowest), lowest, torch.zeros_like(lowest))
    return torch.where(defined, saliency, lowest[batch])

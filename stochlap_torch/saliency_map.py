"""Mesh saliency (Algorithm 2): the log of the difference maps summed over scales."""

from __future__ import annotations

import torch
from torch import Tensor

from .diffusion import ProgressCallback, multiscale_representation
from .mesh import to_mesh_tensors

__all__ = ["mesh_saliency", "saliency_from_differences"]


def saliency_from_differences(differences: Tensor, batch: Tensor | None = None) -> Tensor:
    """``I = log(sum_{k=2..K} D^(k))`` with a finite value where the sum is zero.

    Args:
        differences: ``(K, V)`` difference maps, ``differences[0] = 0``.
        batch: optional ``(V,)`` int64 mesh index of every vertex, for packed batches.

    Returns:
        ``(V,)`` saliency. A vertex whose difference maps are all zero (a vertex with no
        edges, whose row of every ``F^(k)`` is ``e_i``) has no defined logarithm; it gets the
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


def mesh_saliency(
    vertices,
    faces,
    num_scales: int = 8,
    threshold: float = 1e-3,
    max_memory: int | None = None,
    progress: ProgressCallback | None = None,
    batch: Tensor | None = None,
    backend: str = "auto",
    variant: str = "paper",
) -> Tensor:
    """Saliency of every vertex (Algorithm 2, or a variant of :mod:`.variants`).

    Args:
        vertices: ``(V, 3)`` float tensor.
        faces: ``(F, 3)`` integer tensor.
        num_scales: ``K >= 2``.
        threshold: ``lambda`` in ``(0, 1)``.
        max_memory: byte budget for the operators (see
            :func:`~stochlap_torch.diffusion.multiscale_representation`).
        progress: called as ``progress(k, K)`` as the run advances (see
            :func:`~stochlap_torch.diffusion.multiscale_representation`).
        batch: optional ``(V,)`` mesh index of every vertex of a packed batch.
        backend: ``"auto"``, ``"torch"`` or ``"numba"`` (see
            :func:`~stochlap_torch.diffusion.multiscale_representation`).
        variant: ``"paper"`` (Algorithm 2, default) or another name of
            :data:`~stochlap_torch.variants.VARIANTS`.

    Returns:
        ``(V,)`` saliency in the dtype and on the device of ``vertices``; never NaN or Inf.
    """
    from .variants import VARIANTS, saliency_from_representation  # it builds on this module

    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    vertices, faces = to_mesh_tensors(vertices, faces)  # validated by the representation
    rep = multiscale_representation(
        vertices, faces, num_scales, threshold, max_memory=max_memory, progress=progress,
        backend=backend, batch=batch,
    )  # fmt: skip
    return saliency_from_representation(rep, vertices, faces, variant)

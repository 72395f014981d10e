"""Saliency of the robust variant: protrusions at every scale, weighed by area, not vertices.

At each scale the normal displacement ``dn`` (:mod:`stochlap_torch.diffusion.robust`) is
standardised with area-weighted mean and deviation, so that a densely triangulated region
weighs no more than a coarse one, and its positive part (convex bumps, tips of limbs, ridges:
the surface the diffusion pulls inwards) is averaged over the scales. No smoothing, no
valence: the saliency of the same surface meshed twice is the same.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..diffusion.robust_api import RobustRepresentation

__all__ = ["robust_saliency"]


def _per_mesh_mean(values: Tensor, weights: Tensor, batch: Tensor, num_meshes: int) -> Tensor:
    """``(B, T)`` weighted mean of ``(V, T)`` values per mesh."""
    total = weights.new_zeros(num_meshes).index_add_(0, batch, weights).clamp_min(1e-300)
    summed = values.new_zeros(num_meshes, values.shape[1]).index_add_(
        0, batch, values * weights[:, None]
    )
    return summed / total[:, None]


def robust_saliency(rep: RobustRepresentation) -> Tensor:
    """``(V,)`` saliency from a :class:`~stochlap_torch.diffusion.RobustRepresentation`:
    the mean over scales of ``max(0, (dn - mean) / deviation)``, mean and deviation weighted
    by vertex area, per mesh of a batch. Unreferenced vertices (no area) get 0, the value of a
    flat or concave region."""
    dn = rep.dn
    if rep.batch is None:
        batch = torch.zeros(dn.shape[0], dtype=torch.int64, device=dn.device)
    else:
        batch = rep.batch
    num_meshes = int(batch.max()) + 1 if batch.numel() else 1
    mean = _per_mesh_mean(dn, rep.mass, batch, num_meshes)
    centred = dn - mean[batch]
    variance = _per_mesh_mean(centred.square(), rep.mass, batch, num_meshes)
    deviation = variance.clamp_min(torch.finfo(dn.dtype).tiny).sqrt()
    standard = centred / deviation[batch]
    saliency = standard.clamp_min(0.0).mean(dim=1)
    return torch.where(rep.referenced, saliency, torch.zeros_like(saliency))

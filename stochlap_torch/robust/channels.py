"""Saliency and features from the robust representation."""

from __future__ import annotations

import torch
from torch import Tensor

from ..diffusion.robust_api import RobustRepresentation
from ..params import RobustParams

__all__ = ["SPREAD_FLOOR", "robust_channel_names", "robust_features", "robust_saliency"]

#: The spread's eigenvalues are clipped here before the logarithm (the smallest one is 0 on a
#: plane).
SPREAD_FLOOR = 1e-4


def _per_mesh_mean(values: Tensor, weights: Tensor, batch: Tensor, num_meshes: int) -> Tensor:
    """``(B, T)`` weighted mean of ``(V, T)`` values per mesh."""
    total = weights.new_zeros(num_meshes).index_add_(0, batch, weights).clamp_min(1e-300)
    summed = values.new_zeros(num_meshes, values.shape[1]).index_add_(
        0, batch, values * weights[:, None]
    )
    return summed / total[:, None]


def robust_saliency(rep: RobustRepresentation) -> Tensor:
    """``(V,)`` saliency from a :class:`RobustRepresentation`: the mean over scales of ``max(0,
    (dn - mean) / deviation)``, mean and deviation weighted by vertex area (a densely
    triangulated region weighs no more than a coarse one), per mesh of a batch. Unreferenced
    vertices (no area) get 0, the value of a flat or concave region."""
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


def robust_channel_names(params: RobustParams) -> list[str]:
    """Names of the columns :func:`robust_features` returns: ``dn{k}`` (``T``), then
    ``spread{k}_{1,2,3}`` (``3 T``, largest first), then ``heat{k}`` at the scales ``t >=
    heat_from``."""
    scales = range(params.num_scales)
    heat = [k for k, t in enumerate(params.times) if t >= params.heat_from]
    return (
        [f"dn{k}" for k in scales]
        + [f"spread{k}_{axis}" for k in scales for axis in (1, 2, 3)]
        + [f"heat{k}" for k in heat]
    )


def robust_features(rep: RobustRepresentation) -> Tensor:
    """``(V, C)`` features (channel order of :func:`robust_channel_names`); unreferenced
    vertices get the values of a flat plane (0, except the smallest spread: its floor)."""
    spread = torch.log(rep.spread.clamp_min(SPREAD_FLOOR)).flip(-1)  # largest first
    return torch.cat([rep.dn, spread.reshape(spread.shape[0], -1), rep.heat], dim=1)

"""Tensor helpers shared by the mesh, sparse and feature code."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["safe_norm", "to_numpy", "unique_with_inverse"]


def unique_with_inverse(keys: Tensor) -> tuple[Tensor, Tensor]:
    """Sorted unique values of ``(N,)`` int64 ``keys`` and the ``(N,)`` index of each key in them.

    Same as ``torch.unique(keys, sorted=True, return_inverse=True)``, built on one sort:
    torch's CPU ``unique`` is tens of times slower than a sort on small inputs.
    """
    sorted_keys, order = torch.sort(keys)
    starts = torch.ones_like(sorted_keys, dtype=torch.bool)
    starts[1:] = sorted_keys[1:] != sorted_keys[:-1]
    inverse = torch.empty_like(order)
    inverse[order] = torch.cumsum(starts, dim=0) - 1
    return sorted_keys[starts], inverse


def safe_norm(values: Tensor, dim: int) -> Tensor:
    """Euclidean norm along ``dim`` with a zero (not NaN) gradient at the zero vector."""
    squared = values.square().sum(dim=dim)
    tiny = torch.finfo(values.dtype).tiny
    return torch.where(squared > tiny, squared.clamp_min(tiny).sqrt(), torch.zeros_like(squared))


def to_numpy(array) -> np.ndarray:
    """A tensor (detached, on the CPU) or array-like as a numpy array (no copy when possible)."""
    if isinstance(array, Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)

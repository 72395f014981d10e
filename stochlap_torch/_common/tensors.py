"""Tensor helpers shared by the mesh, sparse, feature and robust code."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


def unique_with_inverse(keys: Tensor) -> tuple[Tensor, Tensor]:
    """Sorted unique values of ``(N,)`` int64 ``keys`` and the ``(N,)`` index of each key in
    them: ``torch.unique(keys, sorted=True, return_inverse=True)`` built on one sort (torch's
    CPU ``unique`` is much slower than a sort on small inputs)."""
    sorted_keys, order = torch.sort(keys)
    starts = torch.ones_like(sorted_keys, dtype=torch.bool)
    starts[1:] = sorted_keys[1:] != sorted_keys[:-1]
    inverse = torch.empty_like(order)
    inverse[order] = torch.cumsum(starts, dim=0) - 1
    return sorted_keys[starts], inverse


def to_numpy(array) -> np.ndarray:
    """A tensor (detached, on the CPU) or array-like as a numpy array (no copy when possible)."""
    if isinstance(array, Tensor):
        return array.detach().cpu().numpy()
    return np.asarray(array)


def _eigenvalues(xx, yy, zz, xy, yz, zx) -> Tensor:
    """``(n, 3)`` ascending eigenvalues of symmetric 3 x 3 matrices, in closed form: with ``q``
    the mean of the diagonal, ``p`` the deviation of ``B = A - q I`` and ``r = det(B / p) /
    2``, the eigenvalues are ``q + 2 p cos(acos(r) / 3 + 2 pi j / 3)``."""
    # Scaled to entries of at most 1: det and p^3 neither overflow nor underflow.
    largest = torch.stack([xx, yy, zz, xy, yz, zx]).abs().amax(dim=0)
    scale = torch.where(largest > 0.0, largest, torch.ones_like(largest)).detach()
    xx, yy, zz, xy, yz, zx = (entry / scale for entry in (xx, yy, zz, xy, yz, zx))
    q = (xx + yy + zz) / 3.0
    a, b, c = xx - q, yy - q, zz - q
    p2 = (a * a + b * b + c * c + 2.0 * (xy * xy + yz * yz + zx * zx)) / 6.0
    p = p2.sqrt()
    det = a * (b * c - yz * yz) - xy * (xy * c - yz * zx) + zx * (xy * yz - b * zx)
    cube = (2.0 * p2 * p).clamp_min(torch.finfo(p.dtype).tiny)
    angle = torch.acos(torch.where(p > 0.0, det / cube, 0.0).clamp(-1.0, 1.0)) / 3.0
    top = q + 2.0 * p * torch.cos(angle)
    bottom = q + 2.0 * p * torch.cos(angle + 2.0 * math.pi / 3.0)
    return torch.stack([bottom, 3.0 * q - top - bottom, top], dim=1) * scale[:, None]


class _SymmetricEigenvalues(torch.autograd.Function):
    """:func:`symmetric_eigenvalues` with the gradient of ``torch.linalg.eigvalsh``
    (``sum_i g_i v_i v_i^T``, from the eigenvectors, computed in the backward pass only)."""

    @staticmethod
    def forward(ctx, xx, yy, zz, xy, yz, zx):
        ctx.save_for_backward(xx, yy, zz, xy, yz, zx)
        return _eigenvalues(xx, yy, zz, xy, yz, zx)

    @staticmethod
    def backward(ctx, grad):
        xx, yy, zz, xy, yz, zx = ctx.saved_tensors
        rows = [torch.stack(row, dim=1) for row in ((xx, xy, zx), (xy, yy, yz), (zx, yz, zz))]
        vectors = torch.linalg.eigh(torch.stack(rows, dim=1)).eigenvectors
        outer = (vectors * grad[:, None, :]) @ vectors.transpose(1, 2)
        diagonal = [outer[:, k, k] for k in range(3)]
        return (*diagonal, *(2.0 * outer[:, k, (k + 1) % 3] for k in range(3)))


def symmetric_eigenvalues(xx, yy, zz, xy, yz, zx) -> Tensor:
    """``(n, 3)`` ascending eigenvalues of the symmetric matrices ``[[xx, xy, zx], [xy, yy,
    yz], [zx, yz, zz]]`` (each entry ``(n,)`` float), differentiable like
    ``torch.linalg.eigvalsh``, in closed form (LAPACK solves the matrices one by one).

    The absolute error is a few units of rounding of the matrix's norm, except for two nearly
    equal eigenvalues (the arc cosine near ``+-1``).
    """
    return _SymmetricEigenvalues.apply(xx, yy, zz, xy, yz, zx)

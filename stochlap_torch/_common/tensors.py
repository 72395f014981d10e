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


def _entry_scale(*entries: Tensor) -> Tensor:
    """``(n,)`` the largest absolute entry of each matrix (1 for a zero matrix), detached."""
    largest = torch.stack(entries).abs().amax(dim=0)
    return torch.where(largest > 0.0, largest, torch.ones_like(largest)).detach()


def _eigenvalues(xx, yy, zz, xy, yz, zx) -> Tensor:
    """``(n, 3)`` ascending eigenvalues of symmetric 3 x 3 matrices, in closed form: with ``q``
    the mean of the diagonal, ``p`` the deviation of ``B = A - q I`` and ``r = det(B / p) /
    2``, the eigenvalues are ``q + 2 p cos(acos(r) / 3 + 2 pi j / 3)``."""
    # Scaled to entries of at most 1: det and p^3 neither overflow nor underflow.
    scale = _entry_scale(xx, yy, zz, xy, yz, zx)
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


def _cross(a: tuple, b: tuple) -> tuple:
    """The cross product of two 3-vectors given as ``(x, y, z)`` tuples of ``(n,)`` tensors."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a: tuple, b: tuple) -> Tensor:
    """The dot product of two vectors given as tuples of ``(n,)`` tensors (2 or 3 of them)."""
    total = a[0] * b[0]
    for x, y in zip(a[1:], b[1:], strict=True):
        total = total + x * y
    return total


def _unit(vector: tuple, fallback: tuple) -> tuple:
    """``vector / |vector|`` (a tuple of ``(n,)`` tensors), or ``fallback`` where its length
    is zero."""
    length = _dot(vector, vector).sqrt()
    zero = length == 0.0
    return tuple(
        torch.where(zero, f, c / torch.where(zero, 1.0, length))
        for c, f in zip(vector, fallback, strict=True)
    )


def _eigenvectors(rows: tuple, values: Tensor) -> tuple:
    """The unit eigenvectors ``(v0, v1, v2)`` (each an ``(x, y, z)`` tuple of ``(n,)``) of the
    symmetric matrices with ``rows`` (three ``(x, y, z)`` tuples, entries of at most 1) for
    their ascending ``values`` ``(n, 3)``, in closed form (Eberly, "A Robust Eigensolver for
    3 x 3 Symmetric Matrices"): the eigenvalue farther from the middle one first, as the
    longest cross product of two rows of ``A - lambda I``; the middle one from the 2 x 2
    restriction to the plane orthogonal to it; the last, their cross product. A repeated
    eigenvalue gets some orthonormal basis of its eigenspace."""
    low, middle, high = values.unbind(dim=1)
    top_first = (high - middle) >= (middle - low)
    first = torch.where(top_first, high, low)
    shifted = [
        tuple(entry - first if i == j else entry for j, entry in enumerate(row))
        for i, row in enumerate(rows)
    ]
    first_pair, second_pair = _cross(shifted[0], shifted[1]), _cross(shifted[0], shifted[2])
    third_pair = _cross(shifted[1], shifted[2])
    lengths = [_dot(c, c) for c in (first_pair, second_pair, third_pair)]
    use_first = (lengths[0] >= lengths[1]) & (lengths[0] >= lengths[2])
    use_second = lengths[1] >= lengths[2]
    picked = tuple(
        torch.where(use_first, a, torch.where(use_second, b, c))
        for a, b, c in zip(first_pair, second_pair, third_pair, strict=True)
    )
    one, zero = torch.ones_like(low), torch.zeros_like(low)
    v = _unit(picked, (one, zero, zero))
    # An orthonormal basis (u, w) of the plane orthogonal to v, from v's larger components.
    x_larger = v[0].abs() > v[1].abs()
    u = _unit(
        (
            torch.where(x_larger, -v[2], zero),
            torch.where(x_larger, zero, v[2]),
            torch.where(x_larger, v[0], -v[1]),
        ),
        (zero, zero, one),
    )
    w = _cross(v, u)
    applied_u = tuple(_dot(row, u) for row in rows)
    applied_w = tuple(_dot(row, w) for row in rows)
    m00, m01, m11 = _dot(u, applied_u), _dot(u, applied_w), _dot(w, applied_w)
    # The 2 x 2 eigenvector of the middle value: the longer of its two candidates.
    a = (m01, middle - m00)
    b = (middle - m11, m01)
    longer = _dot(a, a) >= _dot(b, b)
    pair = (torch.where(longer, a[0], b[0]), torch.where(longer, a[1], b[1]))
    c0, c1 = _unit(pair, (one, zero))
    v1 = tuple(c0 * ui + c1 * wi for ui, wi in zip(u, w, strict=True))
    other = _cross(v, v1)
    v0 = tuple(torch.where(top_first, o, vi) for o, vi in zip(other, v, strict=True))
    v2 = tuple(torch.where(top_first, vi, o) for o, vi in zip(other, v, strict=True))
    return v0, v1, v2


class _SymmetricEigenvalues(torch.autograd.Function):
    """:func:`symmetric_eigenvalues` with the gradient of ``torch.linalg.eigvalsh``
    (``sum_i g_i v_i v_i^T``, from eigenvectors in closed form, computed in the backward pass
    only: LAPACK's batched ``eigh`` took a sixth of a training step)."""

    @staticmethod
    def forward(ctx, xx, yy, zz, xy, yz, zx):
        values = _eigenvalues(xx, yy, zz, xy, yz, zx)
        ctx.save_for_backward(xx, yy, zz, xy, yz, zx, values)
        return values

    @staticmethod
    def backward(ctx, grad):
        *entries, values = ctx.saved_tensors
        scale = _entry_scale(*entries)
        xx, yy, zz, xy, yz, zx = (entry / scale for entry in entries)
        rows = ((xx, xy, zx), (xy, yy, yz), (zx, yz, zz))
        vectors = _eigenvectors(rows, values / scale[:, None])
        g = grad.unbind(dim=1)

        def weighted(a: int, b: int) -> Tensor:
            return sum(g[i] * vectors[i][a] * vectors[i][b] for i in range(3))

        diagonal = [weighted(k, k) for k in range(3)]
        return (*diagonal, *(2.0 * weighted(k, (k + 1) % 3) for k in range(3)))


def symmetric_eigenvalues(xx, yy, zz, xy, yz, zx) -> Tensor:
    """``(n, 3)`` ascending eigenvalues of the symmetric matrices ``[[xx, xy, zx], [xy, yy,
    yz], [zx, yz, zz]]`` (each entry ``(n,)`` float), differentiable like
    ``torch.linalg.eigvalsh``, in closed form (LAPACK solves the matrices one by one).

    The absolute error is a few units of rounding of the matrix's norm, except for two nearly
    equal eigenvalues (the arc cosine near ``+-1``).
    """
    return _SymmetricEigenvalues.apply(xx, yy, zz, xy, yz, zx)

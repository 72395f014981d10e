"""The heat semigroup ``exp(-t M^-1 L)`` applied to per-vertex fields, for several times.

No eigendecomposition: the exponential is expanded in Chebyshev polynomials of ``M^-1 L``
scaled to ``[-1, 1]`` (its coefficients are scaled Bessel functions), and one three-term
recurrence serves every time at once; it costs about ``sqrt(t * bound)`` sparse products
with the fields. :func:`heat_apply` works on numpy arrays; :class:`HeatSemigroup` wraps it as
a torch function of the fields, with the operator held constant: ``exp(-t M^-1 L)`` is
self-adjoint in the ``M`` inner product, so its transpose is ``M exp(-t M^-1 L) M^-1`` and the
backward pass is one more application.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .._common.errors import MeshError
from ..operators.heat import HeatOperator

__all__ = ["DEFAULT_TOLERANCE", "HeatSemigroup", "chebyshev_coefficients", "heat_apply"]

#: More Chebyshev terms than this means a level far finer than its scales (a vertex far out
#: from the rest of the mesh: 2.4e7 for one at 1e6 times the mesh's size). The shared meshes
#: need up to 7e4 (octopus), 1.2e6 for the octopus subdivided and decimated.
MAX_CHEBYSHEV_TERMS = 1e7
#: Chebyshev terms are dropped once every time's coefficient is below this.
DEFAULT_TOLERANCE = 1e-6


def chebyshev_coefficients(times: np.ndarray, bound: float, tol: float) -> np.ndarray:
    """``(T, K)`` coefficients of ``exp(-t x)`` on ``[0, bound]`` in the Chebyshev basis of
    ``y = 2 x / bound - 1``: ``c_k = (2 - [k = 0]) (-1)^k e^-a I_k(a)``, ``a = t bound / 2``."""
    from scipy.special import ive

    a = np.asarray(times, dtype=np.float64) * bound / 2.0
    if not np.max(a) <= MAX_CHEBYSHEV_TERMS:
        raise MeshError(
            f"diffusing to the robust variant's scales would take {np.max(a):.3g} steps: the "
            "mesh's triangles differ in size by many orders of magnitude (vertices far out "
            "from the rest?); remove the outlying vertices, or use variant='paper'"
        )
    terms = int(np.max(a) + 12.0 * np.sqrt(np.max(a)) + 30)
    k = np.arange(terms)
    signs = np.where(k % 2 == 0, 1.0, -1.0) * np.where(k == 0, 1.0, 2.0)
    coefficients = ive(k[None, :], a[:, None]) * signs
    kept = np.flatnonzero(np.abs(coefficients).max(axis=0) > tol)
    return coefficients[:, : (kept.max() + 1 if kept.size else 1)]


def heat_apply(
    operator: HeatOperator, fields: np.ndarray, times, tol: float = DEFAULT_TOLERANCE
) -> np.ndarray:
    """``(T, n, C)``: ``exp(-t m^-1 L) fields`` for every ``t`` of ``times`` (``m`` the capped
    masses), by one shared Chebyshev recurrence.

    Args:
        operator: the level's :class:`~stochlap_torch.operators.heat.HeatOperator`.
        fields: ``(n, C)`` float64.
        times: ``(T,)`` diffusion times (in the units of the mesh's area).
        tol: Chebyshev truncation (:data:`DEFAULT_TOLERANCE`).
    """
    coefficients = chebyshev_coefficients(np.asarray(times), operator.bound, tol)
    scale = (2.0 / operator.bound) / operator.capped_mass
    lap = operator.laplacian

    def shifted(y: np.ndarray) -> np.ndarray:  # (2 / bound) m^-1 L y - y
        return scale[:, None] * (lap @ y) - y

    out = coefficients[:, 0, None, None] * fields[None]
    previous, current = fields, shifted(fields)
    for k in range(1, coefficients.shape[1]):
        out += coefficients[:, k, None, None] * current[None]
        previous, current = current, 2.0 * shifted(current) - previous
    return out


class HeatSemigroup(torch.autograd.Function):
    """``(T, n, C)`` ``exp(-t m^-1 L) x`` of ``(n, C)`` fields ``x``, differentiable w.r.t. ``x``
    with the operator held constant (O(n C) memory: nothing but the operator is saved)."""

    @staticmethod
    def forward(ctx, fields: Tensor, operator: HeatOperator, times: tuple, tol: float):
        ctx.operator, ctx.times, ctx.tol = operator, times, tol
        ctx.dtype, ctx.device = fields.dtype, fields.device
        values = fields.detach().cpu().double().numpy()
        out = heat_apply(operator, values, times, tol)
        return torch.from_numpy(out).to(dtype=fields.dtype, device=fields.device)

    @staticmethod
    def backward(ctx, grad: Tensor):
        operator = ctx.operator
        mass = operator.capped_mass
        upstream = grad.detach().cpu().double().numpy() / mass[None, :, None]  # M^-1 g
        total = np.zeros(upstream.shape[1:])
        for index, time in enumerate(ctx.times):
            total += heat_apply(operator, upstream[index], (time,), ctx.tol)[0]
        total *= mass[:, None]
        return torch.from_numpy(total).to(dtype=ctx.dtype, device=ctx.device), None, None, None

"""The ranges a cached value can be in, for refusing corrupt or tampered cache entries."""

from __future__ import annotations

import numpy as np

__all__ = ["check_row_stochastic", "feature_ceiling"]


def feature_ceiling(dtype) -> float:
    """The largest magnitude a cached feature of ``dtype`` may have: the square root of the
    dtype's largest value (float64: 1.3e154, float32: 1.8e19).

    Every channel is dimensionless: a logarithm (saliency, spread, heat: below 1e3 in
    magnitude), a difference map in ``[0, 2]``, or a ratio of two lengths of the mesh
    (coefficients over the mean edge or the bounding box diagonal, normal displacements over
    the square root of a time; with ``normalisation="none"`` a length in units where
    :func:`~stochlap_torch.mesh.extent_scale` keeps the extent below ``2**255`` in float64,
    ``2**31`` in float32). Only a mesh whose lengths span half the dtype's exponent range
    could come near the ceiling, and features are squared in most uses (norms, losses,
    normalisation layers), where a larger value overflows anyway. In a cache file, a value
    beyond it is corruption or tampering.
    """
    return float(np.sqrt(np.finfo(dtype).max))


def check_row_stochastic(name: str, crow: np.ndarray, val: np.ndarray) -> None:
    """Raise ``ValueError`` (naming ``name``) unless the finite CSR values ``val`` (rows
    ``crow``) lie in ``[0, 1]`` and every row sums to 1, both within ``sqrt(eps)`` of the dtype
    (1.5e-8 in float64, 3.5e-4 in float32): every ``F^(k)`` sums its rows to 1 within a few
    ``eps``, and summing even thousands of entries here adds little more."""
    tolerance = float(np.sqrt(np.finfo(val.dtype).eps))
    if val.size and (val.min() < 0 or val.max() > 1 + tolerance):
        raise ValueError(f"{name}: values outside [0, 1]")
    num_rows = crow.shape[0] - 1
    rows = np.repeat(np.arange(num_rows), np.diff(crow))
    sums = np.bincount(rows, weights=val.astype(np.float64), minlength=num_rows)
    if sums.size and np.abs(sums - 1).max() > tolerance:
        raise ValueError(f"{name}: rows do not sum to 1")

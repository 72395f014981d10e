"""The intrinsic Delaunay cotangent Laplacian's edge weights and lumped areas (the robust
variant's heat operator, :mod:`stochlap_torch.robust.heat`, and the Laplacian baselines build
on them)."""

from __future__ import annotations

import numpy as np

from .. import _kernels
from .._common.errors import MissingDependencyError

__all__ = ["intrinsic_delaunay_weights"]


def intrinsic_delaunay_weights(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edge weights and lumped areas of the intrinsic Delaunay cotangent Laplacian.

    robust-laplacian's operator (mollified lengths, tufted cover): on a closed, oriented,
    edge-manifold mesh the library's own flips compute it (:func:`~stochlap_torch._kernels.
    intrinsic_delaunay`, the same matrix to rounding, several times faster); robust-laplacian
    builds it for any other mesh.

    Args:
        vertices: ``(n, 3)`` float64; faces: ``(m, 3)`` int64 (robust-laplacian's input).

    Returns:
        ``(edges (E, 2) int64 with i < j, weights (E,) float64 >= 0, mass (n,) float64)``: the
        edges of the intrinsic triangulation (which may join vertices no face joins), their
        weights ``W_ij = -L_ij`` (rounding below zero clamped) and the vertex areas.
    """
    vertices = np.ascontiguousarray(vertices, dtype=np.float64)
    faces = np.ascontiguousarray(faces)
    flipped = _kernels.intrinsic_delaunay(vertices, faces)
    if flipped is not None:
        rows, cols, weights, mass = flipped
    else:
        rows, cols, weights, mass = _robust_laplacian(vertices, faces)
    # One int64 key per vertex pair (the library's edge keys): one sort, not np.unique over
    # rows and an unbuffered np.add.at.
    count = vertices.shape[0]
    keys = np.minimum(rows, cols).astype(np.int64) * count + np.maximum(rows, cols)
    pairs, inverse = np.unique(keys, return_inverse=True)
    summed = np.bincount(inverse.reshape(-1), weights=weights, minlength=pairs.size)
    edges = np.stack([pairs // count, pairs % count], axis=1)
    return edges, np.maximum(summed, 0.0), mass


def _robust_laplacian(vertices: np.ndarray, faces: np.ndarray):
    """``(rows, cols, weights, mass)`` from robust-laplacian (any mesh)."""
    try:
        import robust_laplacian
    except ImportError as error:  # pragma: no cover - a dependency of the package
        raise MissingDependencyError(
            "the robust variant needs robust-laplacian: pip install robust-laplacian"
        ) from error
    from scipy import sparse

    laplacian, mass = robust_laplacian.mesh_laplacian(vertices, faces)
    upper = sparse.triu(laplacian, k=1).tocoo()
    weights = -np.asarray(upper.data, dtype=np.float64)
    return upper.row, upper.col, weights, np.asarray(mass.diagonal(), dtype=np.float64)

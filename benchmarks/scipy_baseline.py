"""A straightforward scipy.sparse implementation of Algorithms 1 and 2: the speed baseline.

This is what one would write first with scipy: whole-matrix sparse operations, one after the
other, with every intermediate materialised::

    edges  = unique undirected edges of the faces
    W      = 1 / |Pi - Pj|^2 on the edges (symmetric)
    Lhat   = diag(W 1) + W                                  (csr)
    F      = rownorm(Lhat)                                  (F^(1))
    for k = 2..K:
        G  = rownorm(F @ Lhat)
        G.data[G.data < lambda] = 0; G.eliminate_zeros()   (each row's maximum is kept)
        G  = rownorm(G @ diags(alpha))
        P_k = G @ P;  D_k = |G - F|.sum(1);  F = G
    saliency = log(sum_k D_k)

``rownorm(X) = diags(1 / X.sum(1)) @ X``. It follows the library's numerics contract
(``tests/reference.py``): ``alpha(i) = c n_i / sum_j |Pi - Pj| + 1`` with ``c`` the mean unique
edge length, a vertex without edges gets ``Lhat(i, i) = 1`` and ``alpha(i) = 1``, and the
threshold keeps the largest entry of every row (that only matters when a row holds more than
``1 / lambda`` entries, all below ``lambda``). scipy.sparse runs on one thread.

Nothing here imports the library: :func:`multiscale_scipy` takes NumPy arrays (or anything
``np.asarray`` accepts, torch CPU tensors included) and returns NumPy arrays.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

__all__ = ["ScipyMultiscale", "multiscale_scipy", "stochastic_operators"]


@dataclass
class ScipyMultiscale:
    """Output of :func:`multiscale_scipy` for ``K`` scales and ``V`` vertices.

    Attributes:
        positions: ``(K, V, 3)``; ``positions[0] = P``, ``positions[k-1] = F^(k) P``.
        differences: ``(K, V)``; ``differences[0] = 0``,
            ``differences[k-1] = sum_j |F^(k) - F^(k-1)|(i, j)``.
        saliency: ``(V,)`` ``log(sum_k D^(k))`` (Algorithm 2).
        nnz: ``K`` stored entries of ``F^(1..K)``.
    """

    positions: np.ndarray
    differences: np.ndarray
    saliency: np.ndarray
    nnz: list[int]

    def entries_per_row(self) -> list[float]:
        """Mean stored entries per row of each ``F^(k)``."""
        return [n / self.positions.shape[1] for n in self.nnz]


def _rownorm(matrix: sp.csr_matrix) -> sp.csr_matrix:
    """Every row divided by its sum (``diags(1 / rowsum) @ X``)."""
    return (sp.diags(1.0 / np.asarray(matrix.sum(axis=1)).ravel()) @ matrix).tocsr()


def stochastic_operators(vertices, faces) -> tuple[sp.csr_matrix, np.ndarray]:
    """``Lhat = |D - W|`` as csr and ``alpha`` of Eq. 9, from a triangle mesh.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int.

    Returns:
        ``(Lhat, alpha)``: ``(V, V)`` float64 csr and ``(V,)`` float64.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    num_vertices = vertices.shape[0]
    pairs = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    pairs.sort(axis=1)
    keys = np.unique(pairs[:, 0] * num_vertices + pairs[:, 1])
    first, second = keys // num_vertices, keys % num_vertices

    lengths = np.linalg.norm(vertices[first] - vertices[second], axis=1)
    weights = 1.0 / lengths**2
    upper = sp.coo_matrix((weights, (first, second)), shape=(num_vertices, num_vertices))
    adjacency = (upper + upper.T).tocsr()
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    degree[degree == 0] = 1.0  # a vertex without edges: Lhat(i, i) = 1
    lhat = (sp.diags(degree) + adjacency).tocsr()

    count = np.bincount(first, minlength=num_vertices) + np.bincount(second, minlength=num_vertices)
    total = np.bincount(first, lengths, num_vertices) + np.bincount(second, lengths, num_vertices)
    alpha = np.ones(num_vertices)
    has_edges = count > 0
    alpha[has_edges] += lengths.mean() * count[has_edges] / total[has_edges]
    return lhat, alpha


def multiscale_scipy(vertices, faces, num_scales: int = 8, threshold: float = 1e-3):
    """Algorithms 1 and 2 with scipy.sparse; see the module docstring.

    Args:
        vertices: ``(V, 3)`` float.
        faces: ``(F, 3)`` int.
        num_scales: ``K >= 2``.
        threshold: ``lambda``.

    Returns:
        :class:`ScipyMultiscale`.
    """
    points = np.asarray(vertices, dtype=np.float64)
    lhat, alpha = stochastic_operators(points, faces)
    scale_alpha = sp.diags(alpha)

    current = _rownorm(lhat)
    positions = [points]
    differences = [np.zeros(points.shape[0])]
    nnz = [current.nnz]
    for _ in range(2, num_scales + 1):
        product = _rownorm(current @ lhat)
        row_max = np.repeat(product.max(axis=1).toarray().ravel(), np.diff(product.indptr))
        product.data[(product.data < threshold) & (product.data < row_max)] = 0.0
        product.eliminate_zeros()
        following = _rownorm(product @ scale_alpha)
        positions.append(following @ points)
        differences.append(np.asarray(abs(following - current).sum(axis=1)).ravel())
        nnz.append(following.nnz)
        current = following

    differences = np.stack(differences)
    total = differences.sum(axis=0)
    defined = total > 0
    saliency = np.log(np.where(defined, total, 1.0))
    if not defined.all():  # a vertex without edges: the smallest defined saliency (or 0)
        saliency[~defined] = saliency[defined].min() if defined.any() else 0.0
    return ScipyMultiscale(np.stack(positions), differences, saliency, nnz)

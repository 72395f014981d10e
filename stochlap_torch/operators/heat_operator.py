"""The heat operator of a mesh: an intrinsic-Delaunay cotangent Laplacian and lumped areas.

``exp(-t M^-1 L)`` approximates heat diffusion on the surface for any triangulation when
``L`` is built on the intrinsic Delaunay triangulation (robust-laplacian: its cotangent
weights are never negative, where the plain cotangent Laplacian of a decimated or graded mesh
has a fifth of its weights negative) and ``M`` holds the vertices' areas. A few vertices much
smaller than their neighbourhood (slivers, decimation clusters, near-coincident pairs) would
make ``M^-1 L`` stiff, and the cost of applying the semigroup grows with the stiffness: the
edges that couple their vertices much faster than the median edge are clamped
(:func:`clamped_weights`), then the mass of any vertex still far stiffer than the median is
raised (:func:`capped_mass`). The masses stay the areas wherever the clamp suffices.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from .. import _kernels
from .._common.errors import MeshError, MissingDependencyError

__all__ = [
    "DEFAULT_CAP",
    "DEFAULT_CLAMP",
    "HeatOperator",
    "capped_mass",
    "chebyshev_terms",
    "clamped_weights",
    "heat_operator",
    "intrinsic_delaunay_weights",
]

#: A vertex's mass is raised until its stiffness ``D/M`` is at most this many times the median
#: (:func:`capped_mass`).
DEFAULT_CAP = 8.0
#: An edge couples its vertices at most this many times faster than the median edge
#: (:func:`clamped_weights`): high enough to leave the edges of well-shaped levels alone, low
#: enough that near-coincident vertex pairs (which decimation leaves) do not need raised
#: masses, which would make them heat reservoirs (``benchmarks/ROBUST.md`` compares values).
DEFAULT_CLAMP = 32.0


@dataclass(frozen=True)
class HeatOperator:
    """``M^-1 L`` of one mesh, as the heat semigroup needs it.

    Attributes:
        laplacian: ``(n, n)`` scipy CSR ``L = D - W``, symmetric positive semi-definite (``W``
            the :func:`clamped_weights`).
        mass: ``(n,)`` lumped vertex areas of the intrinsic triangulation (at least
            ``1e-12`` of their mean).
        capped_mass: ``(n,)`` the masses the semigroup uses (:func:`capped_mass`).
        bound: an upper bound of the spectrum of ``capped_mass^-1 L`` (Gershgorin).
    """

    laplacian: object
    mass: np.ndarray
    capped_mass: np.ndarray
    bound: float

    @property
    def num_vertices(self) -> int:
        return int(self.mass.shape[0])

    @cached_property
    def order(self) -> np.ndarray:
        """``(n,)`` a bandwidth-reducing order of the vertices (reverse Cuthill-McKee): the
        semigroup runs on :attr:`recurrence`, whose neighbours lie close in memory, so a sparse
        product reads the fields in cache-friendly runs. Computed once."""
        from scipy.sparse.csgraph import reverse_cuthill_mckee

        return np.asarray(
            reverse_cuthill_mckee(self.laplacian, symmetric_mode=True), dtype=np.int64
        )

    @cached_property
    def recurrence(self):
        """``(n, n)`` scipy CSR ``R = 2 ((2 / bound) m^-1 L - I)`` in :attr:`order` (``m`` the
        capped masses), sorted indices: the matrix of the Chebyshev recurrence ``T_(k+1) = R
        T_k - T_(k-1)`` of ``m^-1 L`` scaled to ``[-1, 1]`` (one sparse product and one
        subtraction per term). Computed once."""
        from scipy import sparse

        order = self.order
        scale = (4.0 / self.bound) / self.capped_mass[order]
        ordered = self.laplacian[order][:, order]
        matrix = (sparse.diags(scale) @ ordered - 2.0 * sparse.identity(order.size)).tocsr()
        matrix.sort_indices()
        return matrix


def chebyshev_terms(scaled_time: float, tol: float) -> int:
    """The Chebyshev terms of ``exp(-t x)`` on ``[0, bound]`` kept at truncation ``tol``, ``a =
    t bound / 2`` the ``scaled_time``: one more than the last ``k`` whose coefficient ``|c_k|
    = (2 - [k = 0]) e^-a I_k(a)`` exceeds ``tol`` (at least 1). ``I_k(a)`` decreases in ``k``,
    so a bisection over ``k >= 1`` finds it, up to ``a + 12 sqrt(a) + 30`` (where the
    coefficients are below ``1e-30``): about ``sqrt(a)`` terms, not ``a``. The heat
    semigroup's coefficient table (:func:`~stochlap_torch.diffusion.semigroup.
    chebyshev_coefficients`) is this wide, and the robust variant's budget counts it."""
    from scipy.special import ive

    def above(k: int) -> bool:
        return 2.0 * float(ive(k, scaled_time)) > tol

    if not above(1):
        return 1
    low, high = 1, int(scaled_time + 12.0 * math.sqrt(scaled_time) + 30)
    while high - low > 1:  # above(low), and not above(high)
        middle = (low + high) // 2
        low, high = (middle, high) if above(middle) else (low, middle)
    return low + 1


def _median_ratio(numerator: np.ndarray, denominator: np.ndarray) -> float:
    """The median of ``numerator / denominator`` where both are positive (1 if nowhere)."""
    usable = (numerator > 0.0) & (denominator > 0.0)
    return float(np.median(numerator[usable] / denominator[usable])) if usable.any() else 1.0


def _floored(mass: np.ndarray) -> np.ndarray:
    """``mass`` raised to at least ``1e-12`` of its mean (no vertex without mass)."""
    return np.maximum(mass, 1e-12 * max(float(mass.mean()) if mass.size else 1.0, 1e-300))


def clamped_weights(
    edges: np.ndarray, weights: np.ndarray, mass: np.ndarray, clamp: float = DEFAULT_CLAMP
) -> np.ndarray:
    """``(E,)`` the edge weights with every edge's rate ``W_ij / min(M_i, M_j)`` clamped to
    ``clamp`` times the median rate.

    Two vertices much closer together than their neighbours (quadric decimation leaves such
    pairs) share a huge cotangent weight (up to 8e5 times the median) and have tiny areas.
    Raising their masses instead (:func:`capped_mass` alone, as before) made them heat
    reservoirs: on a subdivided, then decimated gargoyle the raised masses summed to 9 to 19
    times the surface area on the levels the scales ran on, and the features of that copy
    kept a rank correlation of 0.73 with the original's (0.99 with this clamp and the heat
    channel on the true areas). Clamped, such a pair still equilibrates ``clamp`` times
    faster than a typical edge, so within a small fraction of the smallest scale, and the mass
    cap that follows raises its masses by a few times at most, not hundreds.

    Args:
        edges: ``(E, 2)`` int64 vertex pairs; weights: ``(E,)`` float64 ``W_ij >= 0``;
        mass: ``(n,)`` float64 vertex areas; clamp: the largest rate, in median rates.
    """
    smaller = np.minimum(mass[edges[:, 0]], mass[edges[:, 1]])
    return np.minimum(weights, clamp * _median_ratio(weights, smaller) * smaller)


def capped_mass(laplacian, mass: np.ndarray, cap: float = DEFAULT_CAP) -> tuple[np.ndarray, float]:
    """``(m, bound)``: ``m = max(M, D / (cap median(D / M)))`` and ``2 max(D / m)``, a bound of
    the spectrum of ``m^-1 L`` (Gershgorin), which sets the cost of :func:`~stochlap_torch.
    diffusion.semigroup.heat_apply`."""
    diagonal = laplacian.diagonal()
    capped = np.maximum(_floored(mass), diagonal / (cap * _median_ratio(diagonal, mass)))
    with np.errstate(divide="ignore", invalid="ignore"):  # heat_operator checks the result
        bound = 2.0 * float(np.max(diagonal / capped)) if diagonal.size else 1.0
    return capped, max(bound, 1e-300)


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


def heat_operator(
    vertices: np.ndarray,
    faces: np.ndarray,
    cap: float = DEFAULT_CAP,
    clamp: float = DEFAULT_CLAMP,
) -> HeatOperator:
    """The :class:`HeatOperator` of a mesh (``(n, 3)`` float64, ``(m, 3)`` int64, every vertex
    referenced); ``clamp`` for :func:`clamped_weights`, then ``cap`` for :func:`capped_mass`."""
    from scipy import sparse

    edges, weights, lumped = intrinsic_delaunay_weights(vertices, faces)
    lumped = _floored(lumped)
    weights = clamped_weights(edges, weights, lumped, clamp)
    # Rebuild L = D - W from the clamped weights so that L 1 = 0 exactly.
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    n = vertices.shape[0]
    w = sparse.csr_matrix((np.concatenate([weights, weights]), (rows, cols)), shape=(n, n))
    lap = (sparse.diags(np.asarray(w.sum(axis=1)).ravel()) - w).tocsr()
    capped, bound = capped_mass(lap, lumped, cap)
    if not (np.isfinite(bound) and np.isfinite(capped).all() and capped.min() > 0.0):
        raise MeshError(
            "the robust variant's heat operator is not finite on this mesh: its triangles "
            "differ in size by more than floating point holds; remove the outlying vertices, "
            "or use variant='paper'"
        )
    return HeatOperator(lap, lumped, capped, bound)

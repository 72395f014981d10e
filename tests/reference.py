"""A plain dense float64 NumPy reference of the numerics contract.

Everything here is written for clarity, not speed: dense ``(V, V)`` matrices and Python loops.
It is only meant for meshes of a few hundred vertices. The library is compared against it in
``test_reference.py``, ``test_interest.py`` and ``test_real_meshes.py``; it never imports the
library. The end of the file holds the small synthetic test meshes shared by the test modules.

Contract (paper Sec. 3.2-3.4, Algorithms 1 and 2, Sec. 4.5):

* ``W(i, j) = 1 / |Pi - Pj|^2`` on the unique undirected edges of the faces,
  ``Lhat = |D - W|`` (diagonal ``D_ii``, off-diagonal ``W_ij``); a vertex without edges gets
  ``Lhat_ii = 1``.
* ``F1 = rownorm(Lhat)``; for ``k = 2..K``: ``G = rownorm(F(k-1) @ Lhat)``, zero entries strictly
  below the threshold except the largest entry of each row, scale column ``j`` by ``alpha(j)``,
  ``F(k) = rownorm(G)``.
* ``positions[0] = P``, ``positions[k-1] = F(k) P``; ``coefficients[k-1] = positions[k-2] -
  positions[k-1]``; ``differences[k-1] = rowsum |F(k) - F(k-1)|`` (index 0 is zero for both).
* ``saliency = log(sum_k differences)``; a vertex whose sum is exactly zero gets the minimum
  saliency of the other vertices (``0.0`` if there are none).
* Interest points: 1-ring maxima (``>=``) at or above ``min + t_global (max - min)``, by
  descending saliency ("paper" mode); "nms" mode accepts them greedily unless an accepted point
  lies within graph-geodesic distance ``radius * bbox diagonal`` (plain Dijkstra).
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

__all__ = [
    "SMALL_MESH_BUILDERS",
    "ReferenceResult",
    "SmallMesh",
    "alpha",
    "bbox_diagonal",
    "dijkstra",
    "edge_lengths",
    "heat_apply",
    "icosphere",
    "interest_points_nms",
    "interest_points_paper",
    "lhat",
    "multiscale",
    "neighbours",
    "noisy_sphere",
    "open_grid",
    "rim_vertices",
    "row_normalise",
    "saliency_from_differences",
    "stochastic_laplacian",
    "threshold_keep_max",
    "to_numpy",
    "two_components",
    "unique_edges",
    "with_unreferenced_vertex",
]


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges ``(E, 2)`` with ``i < j``, sorted lexicographically."""
    edges = set()
    for face in np.asarray(faces, dtype=np.int64):
        for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            edges.add((int(min(a, b)), int(max(a, b))))
    return np.array(sorted(edges), dtype=np.int64).reshape(-1, 2)


def edge_lengths(vertices: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Euclidean length of each edge."""
    vertices = np.asarray(vertices, dtype=np.float64)
    return np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)


def neighbours(num_vertices: int, faces: np.ndarray) -> list[set[int]]:
    """1-ring neighbourhood of every vertex (a list of sets)."""
    ring: list[set[int]] = [set() for _ in range(num_vertices)]
    for i, j in unique_edges(faces):
        ring[i].add(int(j))
        ring[j].add(int(i))
    return ring


def lhat(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Dense ``|L|`` with ``L = D - W``, ``W_ij = 1/|Pi-Pj|^2``; isolated vertices get ``1``."""
    vertices = np.asarray(vertices, dtype=np.float64)
    num = vertices.shape[0]
    matrix = np.zeros((num, num))
    for i, j in unique_edges(faces):
        weight = 1.0 / float(np.sum((vertices[i] - vertices[j]) ** 2))
        matrix[i, j] = weight
        matrix[j, i] = weight
    for i in range(num):
        row_sum = matrix[i].sum()
        matrix[i, i] = row_sum if row_sum > 0 else 1.0
    return matrix


def row_normalise(matrix: np.ndarray) -> np.ndarray:
    """Divide every row by its sum (rows are assumed to have a positive sum)."""
    return matrix / matrix.sum(axis=1, keepdims=True)


def stochastic_laplacian(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The stochastic mesh Laplacian ``[Lhat]_r`` (Eq. 5)."""
    return row_normalise(lhat(vertices, faces))


def alpha(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Scale invariance function of Eq. 9; ``c`` is the mean unique edge length.

    ``alpha(i) = c * n_i / sum_{j in N(i)} |Pi - Pj| + 1``; isolated vertices get ``1``.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    edges = unique_edges(faces)
    lengths = edge_lengths(vertices, edges)
    c = lengths.mean()
    count = np.zeros(vertices.shape[0])
    total = np.zeros(vertices.shape[0])
    for (i, j), length in zip(edges, lengths, strict=True):
        for v in (i, j):
            count[v] += 1
            total[v] += length
    out = np.ones(vertices.shape[0])
    has_edges = count > 0
    out[has_edges] = c * count[has_edges] / total[has_edges] + 1.0
    return out


def threshold_keep_max(matrix: np.ndarray, threshold: float) -> np.ndarray:
    """Zero the entries strictly below ``threshold``, keeping each row's largest entry.

    Ties for the largest entry are all kept; tests that exercise this branch use meshes with
    random noise, so ties do not occur there.
    """
    out = np.where(matrix < threshold, 0.0, matrix)
    row_max = matrix.max(axis=1, keepdims=True)
    return np.where(matrix == row_max, matrix, out)


@dataclass
class ReferenceResult:
    """Dense outputs of Algorithms 1 and 2."""

    operators: list[np.ndarray]  # F(1) .. F(K), each (V, V)
    positions: np.ndarray  # (K, V, 3)
    coefficients: np.ndarray  # (K, V, 3)
    differences: np.ndarray  # (K, V)
    alpha: np.ndarray  # (V,)
    #: smallest ``|G - threshold| / threshold`` over the nonzero entries of every normalised
    #: product ``G``: near 0, rounding decides whether an entry survives, so an exact
    #: comparison with another implementation is ill-posed (tests check it is not tiny).
    threshold_margin: float = np.inf

    @property
    def saliency(self) -> np.ndarray:
        """Algorithm 2 with the documented fallback for zero sums."""
        return saliency_from_differences(self.differences)


def multiscale(
    vertices: np.ndarray, faces: np.ndarray, num_scales: int = 8, threshold: float = 1e-3
) -> ReferenceResult:
    """Algorithm 1 (and the difference maps of Algorithm 2), densely, in float64."""
    points = np.asarray(vertices, dtype=np.float64)
    l_hat = lhat(points, faces)
    scale = alpha(points, faces)
    operators = [row_normalise(l_hat)]
    positions = [points.copy()]
    coefficients = [np.zeros_like(points)]
    differences = [np.zeros(points.shape[0])]
    margin = np.inf
    for _ in range(2, num_scales + 1):
        previous = operators[-1]
        g = row_normalise(previous @ l_hat)
        margin = min(margin, float(np.min(np.abs(g[g > 0] - threshold))) / threshold)
        g = threshold_keep_max(g, threshold)
        g = g * scale[None, :]
        current = row_normalise(g)
        operators.append(current)
        positions.append(current @ points)
        coefficients.append(positions[-2] - positions[-1])
        differences.append(np.abs(current - previous).sum(axis=1))
    return ReferenceResult(
        operators=operators,
        positions=np.stack(positions),
        coefficients=np.stack(coefficients),
        differences=np.stack(differences),
        alpha=scale,
        threshold_margin=margin,
    )


def heat_apply(operator, fields: np.ndarray, times, tol: float = 1e-6) -> np.ndarray:
    """``(T, n, C)`` ``exp(-t m^-1 L) fields`` for every ``t`` of ``times``, by the plain
    Chebyshev recurrence the robust variant's semigroup computes in blocks (an oracle for it).

    ``operator`` has the robust heat operator's ``recurrence`` (scipy CSR ``R = 2 y``, ``y =
    (2 / bound) m^-1 L - I``, in the vertex ``order``), ``order`` and ``bound``. With ``a = t
    bound / 2``, ``exp(-t m^-1 L) = sum_k c_k T_k(y)``, ``c_k = (2 - [k = 0]) (-1)^k e^-a
    I_k(a)``; every time keeps the terms up to the last one any time has above ``tol``.
    """
    from scipy.special import ive

    scaled = np.asarray(times, dtype=np.float64) * operator.bound / 2.0
    width = int(scaled.max() + 12.0 * np.sqrt(scaled.max()) + 30)
    k = np.arange(width)
    table = ive(k[None, :], scaled[:, None]) * np.where(k == 0, 1.0, 2.0)
    kept = np.flatnonzero((table > tol).any(axis=0))
    terms = int(kept.max()) + 1 if kept.size else 1
    coefficients = table[:, :terms] * np.where(k[:terms] % 2 == 0, 1.0, -1.0)
    order, matrix = operator.order, operator.recurrence
    previous, current = fields[order], 0.5 * (matrix @ fields[order])
    sums = coefficients[:, 0, None, None] * previous[None]
    for index in range(1, terms):
        sums += coefficients[:, index, None, None] * current[None]
        previous, current = current, matrix @ current - previous
    out = np.empty_like(sums)
    out[:, order] = sums
    return out


def saliency_from_differences(differences: np.ndarray) -> np.ndarray:
    """``log(sum_k differences)``; exact-zero sums get the minimum of the other vertices."""
    total = np.asarray(differences, dtype=np.float64).sum(axis=0)
    positive = total > 0
    out = np.zeros_like(total)
    out[positive] = np.log(total[positive])
    fallback = out[positive].min() if positive.any() else 0.0
    out[~positive] = fallback
    return out


def _referenced(num_vertices: int, faces: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: the vertex belongs to at least one edge."""
    mask = np.zeros(num_vertices, dtype=bool)
    mask[np.asarray(faces, dtype=np.int64).ravel()] = True
    return mask


def rim_vertices(num_vertices: int, faces: np.ndarray) -> set[int]:
    """Vertices of a boundary edge: an edge that exactly one face uses."""
    uses: dict[tuple[int, int], int] = {}
    for face in np.asarray(faces, dtype=np.int64).tolist():
        for a, b in ((face[0], face[1]), (face[1], face[2]), (face[2], face[0])):
            key = (min(a, b), max(a, b))
            uses[key] = uses.get(key, 0) + 1
    return {v for edge, count in uses.items() if count == 1 for v in edge}


def _ring_maxima(
    saliency: np.ndarray, faces: np.ndarray, t_global: float, include_boundary: bool = False
) -> list[int]:
    """Vertices that are 1-ring maxima (``>=``) and ``>= min + t_global (max - min)``; rim
    vertices (:func:`rim_vertices`) only with ``include_boundary``: they still count as
    neighbours, so a salient rim hides the ring inside it.

    The contract does not say what an isolated vertex (no neighbours) does here. This
    reference reads "interest point" as a point of the surface: vertices without edges are
    never candidates, and the min / max range is taken over vertices with edges. With the
    saliency of Algorithm 2 the range is the same either way (an isolated vertex gets the
    minimum of the others).
    """
    ring = neighbours(saliency.shape[0], faces)
    on_surface = _referenced(saliency.shape[0], faces)
    low, high = float(saliency[on_surface].min()), float(saliency[on_surface].max())
    bar = low + t_global * (high - low)
    rim = set() if include_boundary else rim_vertices(saliency.shape[0], faces)
    return [
        i
        for i in range(saliency.shape[0])
        if ring[i]
        and i not in rim
        and saliency[i] >= bar
        and all(saliency[i] >= saliency[j] for j in ring[i])
    ]


def _by_saliency(indices: list[int], saliency: np.ndarray) -> list[int]:
    """Sort indices by saliency, descending (stable on index for ties)."""
    return sorted(indices, key=lambda i: (-saliency[i], i))


def interest_points_paper(
    saliency: np.ndarray, faces: np.ndarray, t_global: float = 0.4, include_boundary: bool = False
) -> list[int]:
    """Paper mode (Sec. 4.5): 1-ring maxima above ``min + t_global (max - min)``, sorted."""
    saliency = np.asarray(saliency, dtype=np.float64)
    return _by_saliency(_ring_maxima(saliency, faces, t_global, include_boundary), saliency)


def dijkstra(vertices: np.ndarray, faces: np.ndarray, source: int) -> np.ndarray:
    """Shortest-path distance along edges (Euclidean edge lengths) from ``source``."""
    vertices = np.asarray(vertices, dtype=np.float64)
    ring = neighbours(vertices.shape[0], faces)
    dist = np.full(vertices.shape[0], np.inf)
    dist[source] = 0.0
    heap = [(0.0, source)]
    while heap:
        d, i = heapq.heappop(heap)
        if d > dist[i]:
            continue
        for j in ring[i]:
            candidate = d + float(np.linalg.norm(vertices[i] - vertices[j]))
            if candidate < dist[j]:
                dist[j] = candidate
                heapq.heappush(heap, (candidate, j))
    return dist


def bbox_diagonal(vertices: np.ndarray, faces: np.ndarray | None = None) -> float:
    """Bounding-box diagonal of the vertices (only those used by ``faces`` if given)."""
    vertices = np.asarray(vertices, dtype=np.float64)
    if faces is not None:
        vertices = vertices[_referenced(vertices.shape[0], faces)]
    return float(np.linalg.norm(vertices.max(axis=0) - vertices.min(axis=0)))


def interest_points_nms(
    saliency: np.ndarray,
    vertices: np.ndarray,
    faces: np.ndarray,
    radius: float,
    top_k: int | None = None,
    t_global: float = 0.4,
    include_boundary: bool = False,
) -> list[int]:
    """NMS mode: greedy acceptance of 1-ring maxima, far (> r) from accepted points.

    ``r = radius * bbox_diagonal(vertices, faces)``, measured as graph-geodesic distance; a
    candidate is rejected when an accepted point lies at distance ``<= r``.
    """
    saliency = np.asarray(saliency, dtype=np.float64)
    limit = radius * bbox_diagonal(vertices, faces)
    accepted: list[int] = []
    distances: list[np.ndarray] = []
    candidates = _ring_maxima(saliency, faces, t_global, include_boundary)
    for i in _by_saliency(candidates, saliency):
        if top_k is not None and len(accepted) >= top_k:
            break
        if all(d[i] > limit for d in distances):
            accepted.append(i)
            distances.append(dijkstra(vertices, faces, i))
    return accepted


# --------------------------------------------------------------------------------------
# Small test meshes and helpers shared by the test modules
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SmallMesh:
    """A small test mesh as float64 / int64 NumPy arrays."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray

    def tensors(self, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
        """``(vertices, faces)`` as torch tensors, vertices cast to ``dtype``."""
        return (
            torch.tensor(self.vertices, dtype=dtype),
            torch.tensor(self.faces, dtype=torch.int64),
        )


def icosphere(subdivisions: int) -> SmallMesh:
    """trimesh's unit icosphere."""
    sphere = trimesh.creation.icosphere(subdivisions=subdivisions)
    return SmallMesh(
        f"icosphere{subdivisions}",
        np.asarray(sphere.vertices, dtype=np.float64),
        np.asarray(sphere.faces, dtype=np.int64),
    )


def noisy_sphere(seed: int = 0) -> SmallMesh:
    """icosphere(2) with every vertex moved radially by up to +-10 % (no symmetric ties)."""
    base = icosphere(2)
    rng = np.random.default_rng(seed)
    radial = 1.0 + rng.uniform(-0.1, 0.1, size=(base.vertices.shape[0], 1))
    return SmallMesh("noisy_sphere", base.vertices * radial, base.faces)


def open_grid(rows: int = 6, cols: int = 7, seed: int = 1) -> SmallMesh:
    """A triangulated height-field patch with a boundary, slightly jittered."""
    rng = np.random.default_rng(seed)
    xs, ys = np.meshgrid(np.arange(cols, dtype=np.float64), np.arange(rows, dtype=np.float64))
    vertices = np.stack([xs.ravel(), ys.ravel(), np.zeros(rows * cols)], axis=1)
    vertices += rng.uniform(-0.15, 0.15, size=vertices.shape)
    faces = []
    for r in range(rows - 1):
        for c in range(cols - 1):
            a = r * cols + c
            b, d, e = a + 1, a + cols, a + cols + 1
            faces += [(a, b, e), (a, e, d)]
    return SmallMesh("open_grid", vertices, np.asarray(faces, dtype=np.int64))


def with_unreferenced_vertex() -> SmallMesh:
    """icosphere(1) plus one vertex (index 20, in the middle) that no face uses."""
    base = icosphere(1)
    insert_at = 20
    extra = np.array([[0.3, -0.2, 0.1]])
    vertices = np.concatenate([base.vertices[:insert_at], extra, base.vertices[insert_at:]])
    faces = np.where(base.faces >= insert_at, base.faces + 1, base.faces)
    return SmallMesh("unreferenced_vertex", vertices, faces)


def two_components() -> SmallMesh:
    """A jittered icosphere(1) and a smaller, shifted icosahedron (icosphere(0))."""
    rng = np.random.default_rng(7)
    first = icosphere(1)
    second = icosphere(0)
    v1 = first.vertices * (1.0 + rng.uniform(-0.05, 0.05, size=(first.vertices.shape[0], 1)))
    v2 = 0.5 * second.vertices + np.array([3.0, 0.0, 0.0])
    vertices = np.concatenate([v1, v2])
    faces = np.concatenate([first.faces, second.faces + first.vertices.shape[0]])
    return SmallMesh("two_components", vertices, faces)


SMALL_MESH_BUILDERS = {
    "icosphere1": lambda: icosphere(1),
    "icosphere2": lambda: icosphere(2),
    "noisy_sphere": noisy_sphere,
    "open_grid": open_grid,
    "unreferenced_vertex": with_unreferenced_vertex,
    "two_components": two_components,
}


def to_numpy(tensor: torch.Tensor) -> np.ndarray:
    """Detach, move to CPU, convert to float64 NumPy (dense if sparse)."""
    if tensor.layout != torch.strided:
        tensor = tensor.to_dense()
    return tensor.detach().cpu().to(torch.float64).numpy()

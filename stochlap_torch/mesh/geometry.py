"""Geometry and connectivity of a mesh: edges, lengths, normals, valence, orientation, areas,
components; the faces' winding made canonical (:func:`orient_faces`), and triangle soups
refused (:func:`check_not_soup`). The torch functions take ``(V, 3)`` float vertices and
``(F, 3)`` int64 faces (or their unique edges), on any device and dtype, differentiably.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from .._common.errors import MeshError
from .._common.tensors import unique_with_inverse

__all__ = [
    "TriangleSoupError",
    "check_not_soup",
    "connected_components",
    "edge_lengths",
    "extent_scale",
    "face_areas",
    "face_corners",
    "face_normals",
    "is_soup",
    "mean_edge_length",
    "mesh_extent",
    "orient_faces",
    "outward_sign",
    "unique_edges",
    "vertex_degree",
    "vertex_mean_edge_length",
    "vertex_normals",
    "vertex_valence",
]


def safe_norm(values: Tensor, dim: int) -> Tensor:
    """Euclidean norm along ``dim`` with a zero (not NaN) gradient at the zero vector."""
    squared = values.square().sum(dim=dim)
    tiny = torch.finfo(values.dtype).tiny
    return torch.where(squared > tiny, squared.clamp_min(tiny).sqrt(), torch.zeros_like(squared))


def unique_edges(faces: Tensor, num_vertices: int | None = None) -> Tensor:
    """Unique undirected edges of a triangle mesh.

    Args:
        faces: ``(F, 3)`` int64.
        num_vertices: ``V``; defaults to ``faces.max() + 1``.

    Returns:
        ``(E, 2)`` int64, ``edges[:, 0] < edges[:, 1]``, sorted lexicographically.
    """
    return _edges(faces, num_vertices)[0]


def edge_uses(faces: Tensor, num_vertices: int | None = None) -> tuple[Tensor, Tensor]:
    """:func:`unique_edges` and ``(E,)`` int64 how many face sides each is: 1 on a boundary,
    2 inside a manifold surface, more at a non-manifold edge."""
    edges, inverse = _edges(faces, num_vertices)
    return edges, torch.bincount(inverse, minlength=edges.shape[0])


def _edges(faces: Tensor, num_vertices: int | None) -> tuple[Tensor, Tensor]:
    """Unique edges and the ``(3F,)`` index among them of every face side."""
    if num_vertices is None:
        num_vertices = int(faces.max()) + 1
    corners = torch.stack([faces, faces.roll(-1, dims=1)], dim=2).reshape(-1, 2)
    low, high = corners.min(dim=1).values, corners.max(dim=1).values
    keys, inverse = unique_with_inverse(low * num_vertices + high)
    return torch.stack([keys // num_vertices, keys % num_vertices], dim=1), inverse


def connected_components(num_vertices: int, edges: np.ndarray) -> np.ndarray:
    """``(V,)`` int64 component label of every vertex (labels ``0..C-1``) from ``(E, 2)``
    integer edges; a vertex without edges is a component of its own."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    ones = np.ones(edges.shape[0], dtype=np.int8)
    graph = coo_matrix((ones, (edges[:, 0], edges[:, 1])), shape=(num_vertices, num_vertices))
    return scipy_components(graph, directed=False)[1].astype(np.int64)


def edge_graph(points: np.ndarray, edges: np.ndarray):
    """Symmetric ``(V, V)`` scipy CSR matrix of the ``(E, 2)`` unique ``edges`` of the
    ``(V, 3)`` float64 ``points``, weighted by their lengths (for Dijkstra)."""
    from scipy.sparse import coo_matrix

    count, (first, second) = points.shape[0], edges.T
    lengths = np.linalg.norm(points[first] - points[second], axis=1)
    # Built from both directions at once: a sum of matrices would drop the zero-length edges.
    both = (np.concatenate([lengths, lengths]), (np.r_[first, second], np.r_[second, first]))
    return coo_matrix(both, shape=(count, count)).tocsr()


def edge_lengths(vertices: Tensor, edges: Tensor) -> Tensor:
    """``(E,)`` Euclidean lengths of ``(E, 2)`` edges."""
    return (vertices[edges[:, 0]] - vertices[edges[:, 1]]).norm(dim=1)


def vertex_degree(edges: Tensor, num_vertices: int, dtype: torch.dtype) -> Tensor:
    """``(V,)`` number of edges at every vertex, in ``dtype`` (0 for a vertex without edges)."""
    count = torch.zeros(num_vertices, dtype=dtype, device=edges.device)
    ones = torch.ones(edges.shape[0], dtype=dtype, device=edges.device)
    return count.index_add_(0, edges[:, 0], ones).index_add_(0, edges[:, 1], ones)


def vertex_valence(faces: Tensor, num_vertices: int) -> Tensor:
    """``(V,)`` int64 number of distinct 1-ring neighbours of every vertex (0 if unreferenced)."""
    edges = unique_edges(faces, num_vertices)
    return torch.bincount(edges.reshape(-1), minlength=num_vertices)


def mean_edge_length(
    vertices: Tensor, edges: Tensor, batch: Tensor | None = None, lengths: Tensor | None = None
) -> Tensor:
    """Mean length of the ``(E, 2)`` unique ``edges`` of each mesh: ``(1,)``, or ``(B,)`` for a
    packed batch (``batch``: ``(V,)`` int64 mesh indices, ``None``: one mesh; a mesh without
    edges gets 0). ``lengths``: the ``(E,)`` :func:`edge_lengths`, if already computed
    (``None``: computed here)."""
    if lengths is None:
        lengths = edge_lengths(vertices, edges)
    if batch is None:
        return lengths.mean().reshape(1)
    edge_mesh = batch[edges[:, 0]]
    num_meshes = int(batch.max()) + 1
    sums = lengths.new_zeros(num_meshes).index_add_(0, edge_mesh, lengths)
    counts = lengths.new_zeros(num_meshes).index_add_(0, edge_mesh, torch.ones_like(lengths))
    return sums / counts.clamp_min(1)


def vertex_mean_edge_length(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V,)`` mean length of the unique edges at every vertex; 0 for a vertex without edges."""
    num_vertices = vertices.shape[0]
    edges = unique_edges(faces, num_vertices)
    lengths = edge_lengths(vertices, edges)
    total = vertices.new_zeros(num_vertices)
    total.index_add_(0, edges[:, 0], lengths).index_add_(0, edges[:, 1], lengths)
    count = torch.bincount(edges.reshape(-1), minlength=num_vertices).to(vertices.dtype)
    return torch.where(count > 0, total / count.clamp_min(1.0), torch.zeros_like(total))


def face_corners(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3, C)`` ``vertices[faces]``, by ``index_select`` (half the cost on the CPU)."""
    return vertices.index_select(0, faces.reshape(-1)).reshape(-1, 3, vertices.shape[1])


def face_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F, 3)`` face normals scaled by twice the face area (the raw cross products)."""
    corners = face_corners(vertices, faces)
    return torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])


def face_areas(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(F,)`` triangle areas."""
    return 0.5 * face_normals(vertices, faces).norm(dim=1)


def vertex_normals(vertices: Tensor, faces: Tensor) -> Tensor:
    """``(V, 3)`` unit vertex normals: the area-weighted sum of the incident face normals (it
    follows the faces' orientation); zero at a vertex no face uses (or whose face normals
    cancel), with a zero (not NaN) gradient there."""
    cross = face_normals(vertices, faces)
    summed = vertices.new_zeros(vertices.shape).index_add(
        0, faces.reshape(-1), cross.repeat_interleave(3, dim=0)
    )
    length = safe_norm(summed, dim=1).unsqueeze(1)
    return torch.where(
        length > 0,
        summed / length.clamp_min(torch.finfo(length.dtype).tiny),
        torch.zeros_like(summed),
    )


def outward_sign(vertices: Tensor, faces: Tensor, batch: Tensor | None = None) -> Tensor:
    """``(V,)`` ``+1.0`` where the faces of the vertex's mesh are oriented outwards, ``-1.0``
    where inwards, in the dtype of ``vertices``; ``batch``: ``(V,)`` int64 mesh index (``None``:
    one mesh).

    The test is the sign of ``sum_f (a - o) . ((b - o) x (c - o))`` over the faces ``(a, b, c)``
    of a mesh, ``o`` its centroid (six times the enclosed volume for a closed mesh).
    """
    batch, num_meshes = _labels(vertices, batch)
    count = torch.bincount(batch, minlength=num_meshes).clamp_min(1).to(vertices.dtype)
    centre = vertices.new_zeros(num_meshes, 3).index_add_(0, batch, vertices) / count[:, None]
    corners = face_corners(vertices, faces) - centre[batch[faces[:, 0]]].unsqueeze(1)
    triple = (corners[:, 0] * torch.linalg.cross(corners[:, 1], corners[:, 2])).sum(dim=1)
    volume = vertices.new_zeros(num_meshes).index_add_(0, batch[faces[:, 0]], triple)
    return torch.where(volume[batch] < 0, -1.0, 1.0).to(vertices.dtype)


def mesh_extent(vertices: Tensor, batch: Tensor | None = None) -> Tensor:
    """Diagonal of the axis-aligned bounding box of each mesh: ``(1,)``, or ``(B,)`` for a
    ``(V,)`` int64 mesh index ``batch`` (``None``: one mesh)."""
    batch, num_meshes = _labels(vertices, batch)
    index = batch.unsqueeze(1).expand(-1, 3)
    high, low = (
        vertices.new_full((num_meshes, 3), fill).scatter_reduce(0, index, vertices, reduce=how)
        for fill, how in ((-torch.inf, "amax"), (torch.inf, "amin"))
    )
    return safe_norm(high - low, dim=1)


def _labels(vertices: Tensor, batch: Tensor | None) -> tuple[Tensor, int]:
    """``(V,)`` int64 mesh labels (``batch``, or all zero) and the number of meshes."""
    if batch is None:
        batch = torch.zeros(vertices.shape[0], dtype=torch.int64, device=vertices.device)
    return batch, int(batch.max()) + 1 if batch.numel() else 1


def extent_scale(vertices: Tensor) -> float:
    """A power of two ``s`` that brings the bounding box of ``vertices`` into ``[1, 2)``, or
    ``1.0`` when its size is already safe for the dtype (for subnormal coordinates, the
    largest power of two the dtype holds).

    The method is scale invariant and scaling by a power of two is exact, so computing on
    ``s * vertices`` gives the same operators, bit for bit, with no overflow of squared edge
    lengths and no underflow of tiny ones.
    """
    if vertices.numel() == 0:
        return 1.0
    with torch.no_grad():
        extent = float((vertices.amax(dim=0) - vertices.amin(dim=0)).max())
    # Squares of lengths up to 2**safe and their reciprocals stay finite and normal.
    largest = torch.finfo(vertices.dtype).max
    safe = int(math.log2(largest)) // 4
    if not math.isfinite(extent) or extent == 0.0 or -safe <= math.log2(extent) <= safe:
        return 1.0
    return 2.0 ** min(-math.floor(math.log2(extent)), math.frexp(largest)[1] - 1)


class TriangleSoupError(MeshError):
    """The mesh is a triangle soup: most of its faces share no vertex with another face."""


def _face_pairs(faces: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(first (P,), second (P,), same (P,))``: the pairs of faces that share a manifold edge
    (one no other face has), and whether they run along it in the same direction (their
    windings disagree there)."""
    start, end = faces.T.reshape(-1), faces[:, [1, 2, 0]].T.reshape(-1)  # half-edge h: face h % F
    keys = np.minimum(start, end) * count + np.maximum(start, end)
    order = np.argsort(keys)
    keys, forward = keys[order], (start < end)[order]
    equal = keys[1:] == keys[:-1]
    before = np.concatenate([[False], equal[:-1]])
    after = np.concatenate([equal[1:], [False]])
    pair = np.flatnonzero(equal & ~before & ~after)  # runs of exactly two half-edges
    face = order % faces.shape[0]
    return face[pair], face[pair + 1], forward[pair] == forward[pair + 1]


def _patches(num_faces: int, first, second, same):
    """``(patch (F,), lowest (P,), flip (F,) bool)``: the patch of every face (faces joined
    across manifold edges; labels ``0..P-1``), the lowest face of every patch, and whether to
    reverse the face so that it agrees with its patch's lowest face (``None`` if a patch has
    no consistent orientation).

    The pairs define a double cover, a node per face and winding (``2 f`` as given, ``2 f + 1``
    reversed), joined where the windings agree: an orientable patch covers twice, a
    non-orientable one once.
    """
    flipped = same.astype(np.int64)
    rows = np.concatenate([2 * first, 2 * first + 1])
    cols = np.concatenate([2 * second + flipped, 2 * second + 1 - flipped])
    cover = connected_components(2 * num_faces, np.stack([rows, cols], axis=1))
    kept, reversed_ = cover[0::2], cover[1::2]
    _, lowest, patch = np.unique(
        np.minimum(kept, reversed_), return_index=True, return_inverse=True
    )
    patch = patch.reshape(-1)
    if np.any(kept == reversed_):
        return patch, lowest, None
    return patch, lowest, kept != kept[lowest[patch]]


def _tree_flip(num_faces: int, lowest: np.ndarray, first, second, same) -> np.ndarray:
    """``(F,)`` bool: reverse a face where the breadth-first tree from its patch's ``lowest``
    face says so (for a non-orientable patch). The tree follows the faces' adjacency alone, so any
    winding of the input gives the same faces reversed relative to the lowest."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order

    ones = np.ones(first.size, dtype=np.int8)
    graph = coo_matrix((ones, (first, second)), shape=(num_faces,) * 2).tocsr()
    keys = np.minimum(first, second) * num_faces + np.maximum(first, second)
    order = np.argsort(keys)
    keys, same = keys[order], same[order]
    flip = np.zeros(num_faces, dtype=bool)
    for seed in lowest:
        visit, parent = breadth_first_order(graph, int(seed), directed=False)
        child = visit[1:]
        up = parent[child]
        tree_keys = np.minimum(child, up) * num_faces + np.maximum(child, up)
        disagree = same[np.searchsorted(keys, tree_keys)]
        # Parents come before their children in breadth-first order.
        for face, above, swap in zip(child.tolist(), up.tolist(), disagree.tolist(), strict=True):
            flip[face] = flip[above] ^ swap
    return flip


def _patch_volumes(vertices: np.ndarray, faces: np.ndarray, patch: np.ndarray) -> np.ndarray:
    """``(P,)`` six times the signed volume of every patch about its corners' centroid, exactly
    negated when faces are reversed: triple products and centroid are taken over the corners
    sorted by vertex index (with the permutation's sign), never over the winding."""
    count = int(patch.max()) + 1
    ordered = np.sort(faces, axis=1)
    # The permutation from a face to its sorted corners is even when the face is a rotation of
    # them: its smallest corner is followed by the middle one.
    smallest = np.argmin(faces, axis=1)
    follower = faces[np.arange(faces.shape[0]), (smallest + 1) % 3]
    sign = np.where(follower == ordered[:, 1], 1.0, -1.0)
    a, b, c = (vertices[ordered[:, k]] for k in range(3))
    face_sums = a + b + c
    weights = np.bincount(patch, minlength=count) * 3.0
    centre = np.stack([np.bincount(patch, face_sums[:, k], count) for k in range(3)], 1)
    centre = (centre / np.maximum(weights, 1.0)[:, None])[patch]
    a, b, c = a - centre, b - centre, c - centre
    triple = (
        a[:, 0] * (b[:, 1] * c[:, 2] - b[:, 2] * c[:, 1])
        + a[:, 1] * (b[:, 2] * c[:, 0] - b[:, 0] * c[:, 2])
        + a[:, 2] * (b[:, 0] * c[:, 1] - b[:, 1] * c[:, 0])
    )
    return np.bincount(patch, sign * triple, count)


def orient_faces(
    vertices: np.ndarray, faces: np.ndarray, rank: np.ndarray | None = None
) -> np.ndarray:
    """Faces wound one way for every winding of the same surface.

    Every patch of faces joined across manifold edges is oriented consistently, then as a
    whole so that its signed volume about its centroid is positive (where it is exactly zero,
    so that its lowest face started at its corner of least ``rank`` runs on to the lesser of
    the other two). A face is only ever reversed, never rotated: faces wound consistently
    outward come back unchanged.

    Args:
        vertices, faces: ``(V, 3)`` float64 and ``(F, 3)`` int64 arrays.
        rank: ``(V,)`` distinct integers ordering the vertices for the flat tie (default:
            their indices); a rank from the positions makes it follow a renumbering.

    Returns:
        ``(F, 3)`` int64, face ``i`` the corners of input face ``i``, possibly reversed.
    """
    faces = np.asarray(faces, dtype=np.int64)
    if faces.shape[0] == 0:
        return faces.copy()
    count = max(int(faces.max()) + 1, vertices.shape[0])
    first, second, same = _face_pairs(faces, count)
    patch, lowest, flip = _patches(faces.shape[0], first, second, same)
    if flip is None:
        flip = _tree_flip(faces.shape[0], lowest, first, second, same)
    if rank is None:
        rank = np.arange(count)
    oriented = np.where(flip[:, None], faces[:, ::-1], faces)  # reversed, never rotated
    volume = _patch_volumes(vertices, oriented, patch)
    # The flat tie: whether the lowest face, from its corner of least rank, runs on to the
    # greater of the other two.
    low, rows = oriented[lowest], np.arange(lowest.size)
    shift = np.argmin(rank[low], axis=1)
    tie = ~(rank[low[rows, (shift + 1) % 3]] < rank[low[rows, (shift + 2) % 3]])
    reverse = np.where(volume[patch] == 0.0, tie[patch], volume[patch] < 0.0)
    return np.ascontiguousarray(np.where(reverse[:, None], oriented[:, ::-1], oriented))


def isolated_faces(faces: np.ndarray) -> int:
    """The number of faces none of whose vertices belongs to another face."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    uses = np.bincount(faces.reshape(-1))
    return int(np.count_nonzero((uses[faces] == 1).all(axis=1)))


def is_soup(faces: np.ndarray) -> bool:
    """Whether more than half of the faces (of two or more) share no vertex with another face:
    a surface stored as separate triangles (as STL stores it), whose every triangle would be a
    surface of its own."""
    count = int(np.asarray(faces).shape[0])
    return count > 1 and 2 * isolated_faces(faces) > count


def check_not_soup(faces: np.ndarray) -> None:
    """Raise :class:`TriangleSoupError`, naming the counts and the remedy, if :func:`is_soup`."""
    if is_soup(faces):
        count, isolated = int(np.asarray(faces).shape[0]), isolated_faces(faces)
        raise TriangleSoupError(
            f"the mesh is a triangle soup: {isolated} of its {count} faces share no vertex "
            "with another face, so each would be a surface of its own; merge the vertices at "
            "equal positions first (stochlap_torch.mesh.merge_duplicate_vertices; load_mesh "
            "does it for files that are soups, such as STL)"
        )

"""A summary of a mesh: counts, boundaries, components, orientation, and the input checks."""

from __future__ import annotations

import numpy as np
import torch

from .container import Mesh
from .validation import MeshError, validate_mesh

__all__ = ["connected_components", "mesh_report"]


def connected_components(num_vertices: int, edges: np.ndarray) -> np.ndarray:
    """``(V,)`` int64 component label of every vertex (labels ``0..C-1``); a vertex without
    edges is a component of its own.

    Args:
        num_vertices: ``V``.
        edges: ``(E, 2)`` integer vertex pairs.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    graph = coo_matrix(
        (np.ones(edges.shape[0], dtype=np.int8), (edges[:, 0], edges[:, 1])),
        shape=(num_vertices, num_vertices),
    )
    _, labels = scipy_components(graph, directed=False)
    return labels.astype(np.int64)


def mesh_report(mesh: Mesh) -> dict:
    """Counts and checks of a mesh, as printed by ``stochlap info``.

    Returns:
        A JSON-serialisable dict: vertex, face, edge, boundary-edge, non-manifold-edge,
        unreferenced-vertex and component counts, orientation consistency, bounding box,
        mean edge length, and whether :func:`~stochlap_torch.mesh.validate_mesh` passes in
        float64 and in float32 (``True`` or the error message).
    """
    vertices = mesh.vertices.detach().cpu().double().numpy()
    faces = mesh.faces.detach().cpu().numpy().astype(np.int64)
    num_vertices = vertices.shape[0]
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, axis=1)
    edges, per_edge = np.unique(undirected, axis=0, return_counts=True)
    _, per_directed = np.unique(directed, axis=0, return_counts=True)
    referenced = np.zeros(num_vertices, dtype=bool)
    referenced[faces.reshape(-1)] = True
    labels = connected_components(num_vertices, edges)
    num_components = int(np.unique(labels[referenced]).size)
    lengths = np.linalg.norm(vertices[edges[:, 0]] - vertices[edges[:, 1]], axis=1)
    used = vertices[referenced]
    low, high = used.min(axis=0), used.max(axis=0)

    def check(dtype: torch.dtype):
        try:
            validate_mesh(mesh.vertices.to(dtype), mesh.faces)
        except MeshError as exc:
            return str(exc)
        return True

    boundary = int((per_edge == 1).sum())
    non_manifold = int((per_edge > 2).sum())
    return {
        "vertices": int(num_vertices),
        "faces": int(faces.shape[0]),
        "edges": int(edges.shape[0]),
        "boundary_edges": boundary,
        "non_manifold_edges": non_manifold,
        "unreferenced_vertices": int((~referenced).sum()),
        "components": num_components,
        "consistently_oriented": bool((per_directed == 1).all()),
        "closed": boundary == 0 and non_manifold == 0,
        "euler_characteristic": int(referenced.sum()) - int(edges.shape[0]) + int(faces.shape[0]),
        "bbox_min": low.tolist(),
        "bbox_max": high.tolist(),
        "bbox_size": (high - low).tolist(),
        "mean_edge_length": float(lengths.mean()),
        "min_edge_length": float(lengths.min()),
        "valid_float64": check(torch.float64),
        "valid_float32": check(torch.float32),
    }

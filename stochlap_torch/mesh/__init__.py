"""Meshes: the container, input checks, packed batches, files, geometry and vertex orders.

This is the bottom of the data flow: everything else takes a mesh validated here.
"""

from .container import Mesh, MeshBatch, check_batch
from .geometry import (
    connected_components,
    edge_lengths,
    extent_scale,
    face_areas,
    face_corners,
    face_normals,
    mean_edge_length,
    mesh_extent,
    outward_sign,
    unique_edges,
    vertex_degree,
    vertex_mean_edge_length,
    vertex_normals,
    vertex_valence,
)
from .io import (
    bundled_mesh_path,
    from_trimesh,
    load_mesh,
    merge_duplicate_vertices,
    save_ply,
    to_trimesh,
)
from .ordering import LOCALITY_MIN_VERTICES, Renumbering, locality_order
from .surface import TriangleSoupError, check_not_soup, is_soup, orient_faces
from .validation import (
    MeshError,
    as_mesh_tensors,
    mesh_report,
    to_mesh_tensors,
    validate_mesh,
)

__all__ = [
    "LOCALITY_MIN_VERTICES",
    "Mesh",
    "MeshBatch",
    "MeshError",
    "Renumbering",
    "TriangleSoupError",
    "as_mesh_tensors",
    "bundled_mesh_path",
    "check_batch",
    "check_not_soup",
    "connected_components",
    "edge_lengths",
    "extent_scale",
    "face_areas",
    "face_corners",
    "face_normals",
    "from_trimesh",
    "is_soup",
    "load_mesh",
    "locality_order",
    "mean_edge_length",
    "merge_duplicate_vertices",
    "mesh_extent",
    "mesh_report",
    "orient_faces",
    "outward_sign",
    "save_ply",
    "to_mesh_tensors",
    "to_trimesh",
    "unique_edges",
    "validate_mesh",
    "vertex_degree",
    "vertex_mean_edge_length",
    "vertex_normals",
    "vertex_valence",
]

"""Reading and writing mesh files.

:func:`load_mesh` keeps every vertex of the file, referenced or not, in file order, so that
per-vertex outputs line up with the file. OBJ is parsed here (trimesh splits OBJ vertices at
texture seams and drops unreferenced ones); every other format goes through trimesh with
processing switched off.
"""

from __future__ import annotations

import logging
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from .._common.tensors import to_numpy
from .container import Mesh
from .validation import MeshError, as_mesh_tensors, validate_mesh

if TYPE_CHECKING:
    import trimesh

__all__ = [
    "bundled_mesh_path",
    "from_trimesh",
    "load_mesh",
    "merge_duplicate_vertices",
    "save_ply",
    "to_trimesh",
]

logger = logging.getLogger(__name__)


def bundled_mesh_path(name: str = "spot") -> Path:
    """Path of a mesh shipped with the package (``"spot"``: Keenan Crane's cow, public domain)."""
    path = resources.files("stochlap_torch.mesh") / "assets" / f"{name}.obj"
    if not path.is_file():
        raise FileNotFoundError(f"no bundled mesh named {name!r}")
    return Path(str(path))


def load_mesh(path: str | Path, merge_seams: bool = False) -> Mesh:
    """Load a triangle mesh file.

    Args:
        path: an OBJ, OFF, PLY, STL, GLB or any other file trimesh reads as triangles. Polygons
            are fan-triangulated; a scene of several geometries is concatenated.
        merge_seams: merge vertices at identical positions (duplicated at texture or normal
            seams), and drop the faces that collapse. Off by default, so that vertex ``i`` of
            the result is vertex ``i`` of the file.

    Returns:
        A :class:`Mesh` with float64 ``(V, 3)`` vertices and int64 ``(F, 3)`` faces, checked by
        :func:`~stochlap_torch.mesh.validate_mesh`.

    Raises:
        FileNotFoundError: the file does not exist.
        MeshError: the file holds no triangles, or the mesh fails validation.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such mesh file: {path}")
    if path.suffix.lower() == ".obj":
        vertices, faces = _read_obj(path)
    else:
        vertices, faces = _read_with_trimesh(path)
    if merge_seams:
        vertices, faces = merge_duplicate_vertices(vertices, faces)
    mesh = Mesh(torch.from_numpy(vertices), torch.from_numpy(faces))
    validate_mesh(mesh.vertices, mesh.faces)
    logger.info("loaded %s: %d vertices, %d faces", path, mesh.num_vertices, mesh.num_faces)
    return mesh


def merge_duplicate_vertices(
    vertices: np.ndarray, faces: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices with identical positions; drop faces that then repeat a vertex.

    Args:
        vertices: ``(V, 3)`` float array.
        faces: ``(F, 3)`` int array.

    Returns:
        ``(V', 3)`` vertices, first occurrences kept in their original order, and ``(F', 3)``
        faces re-indexed into them.
    """
    _, first, inverse = np.unique(vertices, axis=0, return_index=True, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(first)  # unique rows ranked by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    new_vertices = vertices[first[order]]
    new_faces = rank[inverse][faces]
    keep = (
        (new_faces[:, 0] != new_faces[:, 1])
        & (new_faces[:, 1] != new_faces[:, 2])
        & (new_faces[:, 2] != new_faces[:, 0])
    )
    return new_vertices, np.ascontiguousarray(new_faces[keep])


def _fan(polygon: list[int]) -> list[tuple[int, int, int]]:
    """Fan-triangulate one polygon ``[v0, v1, ..., vn]``."""
    return [(polygon[0], polygon[i], polygon[i + 1]) for i in range(1, len(polygon) - 1)]


def _read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Parse the ``v`` and ``f`` records of an OBJ file (``(V, 3)`` float64, ``(F, 3)`` int64)."""
    vertices: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for line_number, line in enumerate(handle, start=1):
            if line.startswith("v "):
                fields = line.split()
                if len(fields) < 4:
                    raise MeshError(f"{path}:{line_number}: a vertex needs three coordinates")
                vertices.append([float(x) for x in fields[1:4]])
            elif line.startswith("f "):
                polygon = []
                for token in line.split()[1:]:
                    index = int(token.split("/", 1)[0])
                    # OBJ is 1-based; negative indices count back from the latest vertex.
                    polygon.append(index - 1 if index > 0 else len(vertices) + index)
                if len(polygon) < 3:
                    raise MeshError(f"{path}:{line_number}: a face needs at least 3 vertices")
                triangles.extend(_fan(polygon))
    if not triangles:
        raise MeshError(f"{path}: no faces found")
    return np.asarray(vertices, dtype=np.float64).reshape(-1, 3), np.asarray(
        triangles, dtype=np.int64
    )


def _read_with_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Load any trimesh-readable file without merging, reordering or dropping vertices."""
    import trimesh

    try:
        loaded = trimesh.load(path, process=False, maintain_order=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise MeshError(f"{path}: could not be read as a mesh: {exc}") from exc
    geometries = list(loaded.geometry.values()) if isinstance(loaded, trimesh.Scene) else [loaded]
    meshes = [g for g in geometries if isinstance(g, trimesh.Trimesh) and len(g.faces)]
    if not meshes:
        raise MeshError(f"{path}: no triangles found")
    vertices, faces, offset = [], [], 0
    for geometry in meshes:
        vertices.append(np.asarray(geometry.vertices, dtype=np.float64))
        faces.append(np.asarray(geometry.faces, dtype=np.int64) + offset)
        offset += len(geometry.vertices)
    return np.concatenate(vertices), np.concatenate(faces)


def save_ply(
    path: str | Path,
    vertices: torch.Tensor | np.ndarray,
    faces: torch.Tensor | np.ndarray,
    colors: np.ndarray | None = None,
    scalars: dict[str, np.ndarray] | None = None,
) -> Path:
    """Write a binary PLY file keeping every vertex in order.

    Args:
        path: output file.
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.
        colors: optional ``(V, 3)`` or ``(V, 4)`` uint8 vertex colours.
        scalars: optional per-vertex float properties written as ``float`` vertex properties
            (for example ``{"saliency": (V,) array}``).

    Returns:
        The path written.
    """
    path = Path(path)
    vertices = to_numpy(vertices).astype(np.float32)
    faces = to_numpy(faces).astype(np.int32)
    num_vertices = vertices.shape[0]
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    columns = [vertices[:, 0], vertices[:, 1], vertices[:, 2]]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.uint8)
        names = ("red", "green", "blue", "alpha")[: colors.shape[1]]
        for channel, name in enumerate(names):
            fields.append((name, "u1"))
            columns.append(colors[:, channel])
    for name, values in (scalars or {}).items():
        fields.append((name, "<f4"))
        columns.append(np.asarray(to_numpy(values), dtype=np.float32).reshape(num_vertices))
    vertex_table = np.empty(num_vertices, dtype=fields)
    for (name, _), column in zip(fields, columns, strict=True):
        vertex_table[name] = column
    face_table = np.empty(faces.shape[0], dtype=[("n", "u1"), ("v", "<i4", (3,))])
    face_table["n"] = 3
    face_table["v"] = faces
    ply_types = {"<f4": "float", "u1": "uchar"}
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {num_vertices}"]
    header += [f"property {ply_types[kind]} {name}" for name, kind in fields]
    header += [f"element face {faces.shape[0]}", "property list uchar int vertex_indices"]
    header += ["end_header", ""]
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as handle:
        handle.write("\n".join(header).encode("ascii"))
        handle.write(vertex_table.tobytes())
        handle.write(face_table.tobytes())
    return path


def to_trimesh(mesh: Mesh | tuple) -> trimesh.Trimesh:
    """A ``trimesh.Trimesh`` with the same vertices in the same order (``process=False``)."""
    import trimesh

    vertices, faces = (mesh.vertices, mesh.faces) if isinstance(mesh, Mesh) else mesh
    vertices, faces = as_mesh_tensors(vertices, faces)
    return trimesh.Trimesh(
        vertices=vertices.detach().cpu().numpy(), faces=faces.cpu().numpy(), process=False
    )


def from_trimesh(tm, dtype: torch.dtype = torch.float64) -> Mesh:
    """A validated :class:`~stochlap_torch.mesh.Mesh` from a ``trimesh.Trimesh`` (same order).

    Raises:
        MeshError: the trimesh fails :func:`~stochlap_torch.mesh.validate_mesh`.
    """
    vertices = torch.as_tensor(tm.vertices, dtype=dtype).clone()
    faces = torch.as_tensor(tm.faces, dtype=torch.int64).clone()
    return Mesh(*as_mesh_tensors(vertices, faces))

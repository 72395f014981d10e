"""The OBJ reader.

Hand-written because trimesh splits OBJ vertices at texture seams and drops unreferenced ones,
while per-vertex outputs must line up with the file: every ``v`` record is kept, in order.
Only ``v`` and ``f`` records are read; polygons are fan-triangulated.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._common.errors import MeshError

__all__ = ["read_obj"]

#: Larger face indices cannot index any mesh this library can hold (and overflow int64).
_INDEX_LIMIT = 2**62


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Parse the ``v`` and ``f`` records of an OBJ file.

    Returns:
        ``(V, 3)`` float64 vertices and ``(F, 3)`` int64 faces (indices not yet checked
        against ``V``: :func:`~.validation.validate_mesh` does that).

    Raises:
        MeshError: a record that cannot be read (naming the file and the line), or no faces.
    """
    vertices: list[list[float]] = []
    triangles: list[tuple[int, int, int]] = []
    with path.open("r", encoding="utf-8", errors="replace") as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if not fields:
                continue
            if fields[0] == "v":
                vertices.append(_vertex(fields, path, number))
            elif fields[0] == "f":
                triangles.extend(_fan(_polygon(fields, len(vertices), path, number)))
    if not triangles:
        raise MeshError(f"{path}: no faces found (an OBJ mesh needs 'f' records)")
    return (
        np.asarray(vertices, dtype=np.float64).reshape(-1, 3),
        np.asarray(triangles, dtype=np.int64).reshape(-1, 3),
    )


def _vertex(fields: list[str], path: Path, number: int) -> list[float]:
    """The three coordinates of a ``v`` record (a fourth, the weight, is ignored)."""
    if len(fields) < 4:
        raise MeshError(f"{path}:{number}: a vertex needs three coordinates")
    try:
        return [float(x) for x in fields[1:4]]
    except ValueError:
        raise MeshError(
            f"{path}:{number}: vertex coordinates are not numbers: {' '.join(fields[1:4])!r}"
        ) from None


def _polygon(fields: list[str], num_vertices: int, path: Path, number: int) -> list[int]:
    """0-based vertex indices of an ``f`` record (``v``, ``v/vt``, ``v//vn``, ``v/vt/vn``;
    OBJ counts from 1, and negative indices count back from the latest vertex)."""
    polygon = []
    for token in fields[1:]:
        try:
            index = int(token.split("/", 1)[0])
        except ValueError:
            raise MeshError(f"{path}:{number}: face vertex {token!r} is not an index") from None
        if index == 0 or abs(index) >= _INDEX_LIMIT:
            raise MeshError(f"{path}:{number}: face vertex index {index} is out of range")
        polygon.append(index - 1 if index > 0 else num_vertices + index)
    if len(polygon) < 3:
        raise MeshError(f"{path}:{number}: a face needs at least 3 vertices")
    return polygon


def _fan(polygon: list[int]) -> list[tuple[int, int, int]]:
    """Fan-triangulate one polygon ``[v0, v1, ..., vn]``."""
    return [(polygon[0], polygon[i], polygon[i + 1]) for i in range(1, len(polygon) - 1)]

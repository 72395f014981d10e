"""Array conversion and the input checks every figure shares."""

from __future__ import annotations

import math

import numpy as np

from .._common.errors import MeshError, ParameterError


def as_numpy(array, dtype=None) -> np.ndarray:
    """A tensor (detached, on the CPU) or array-like as a numpy array, copied only if needed."""
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    return np.asarray(array, dtype=dtype)


def check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    """``(V, 3)`` float64 vertices and ``(F, 3)`` int64 faces, or :class:`MeshError`."""
    vertices = as_numpy(vertices, np.float64)
    faces = as_numpy(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise MeshError(f"vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise MeshError(f"faces must have shape (F, 3) with F > 0, got {faces.shape}")
    faces = faces.astype(np.int64, copy=False)
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise MeshError(f"face indices must lie in [0, {vertices.shape[0]})")
    return vertices, faces


def used_vertices(faces: np.ndarray, count: int | None = None) -> np.ndarray:
    """The sorted ``(U,)`` int64 indices of the vertices ``(F, 3)`` faces use (``count``: the
    number of vertices, at least ``faces.max() + 1``); ``np.unique`` without its sort or hash."""
    faces = np.asarray(faces, dtype=np.int64).reshape(-1)
    used = np.zeros(int(faces.max()) + 1 if count is None else count, dtype=bool)
    used[faces] = True
    return np.flatnonzero(used)


def check_values(values, num_vertices: int, name: str = "values") -> np.ndarray:
    """``(V,)`` float64 per-vertex values, or :class:`ParameterError`."""
    values = as_numpy(values, np.float64).reshape(-1)
    if values.shape[0] != num_vertices:
        expected = f"one entry per vertex ({num_vertices})"
        raise ParameterError(f"{name} must have {expected}, got {values.shape}")
    return values


#: The dpi a picture may have: below it the fonts vanish (FreeType fails), above it a picture
#: takes minutes and gigabytes.
DPI_RANGE = (10, 600)


def check_dpi(dpi) -> float:
    """``dpi`` as a float in :data:`DPI_RANGE`, or :class:`ParameterError`."""
    try:
        value = float(dpi) if not isinstance(dpi, bool) else math.nan
    except (TypeError, ValueError):
        value = math.nan
    low, high = DPI_RANGE
    if not low <= value <= high:
        raise ParameterError(f"dpi must be a number in [{low}, {high}], got {dpi!r}")
    return value

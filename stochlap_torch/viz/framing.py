"""Camera and framing: which way is up, the drawing frame of a mesh, and the views.

**Which way is up.** ``up`` names a signed axis of the mesh file: ``"x"``, ``"y"``, ``"z"``
(``"+x"`` ... also accepted) or ``"-x"``, ``"-y"``, ``"-z"``. When it is not given
(:func:`guess_up`):

* the axis is the file's ``y`` axis, the convention of OBJ, PLY and glTF files, unless ``y``
  is the smallest extent of the bounding box, in which case the middle extent is taken (so a
  flat mesh lies flat);
* the sign is ``+`` unless the mesh evidently stands on its head: scanned and sculpted
  objects usually rest on a flat base or a planar cut (a pedestal, the bottom of a bust), so
  when the faces that are flat and perpendicular to the axis (normal within about 11 degrees
  of it) and lie at its top (within 2 % of the largest extent) cover at least 0.5 % of the
  surface and four times the area of the same kind of faces at its bottom, the axis is
  flipped. Without such evidence the file's own ``+`` direction is kept, so a mesh is never
  turned over on a weak hint.

On the 21 shared test meshes (``/work/shared/meshes``, the two derived Loop meshes aside) this
turns ``gargoyle_50k.off``, stored upside down, the right way up and leaves the other 20 as
their files have them: 12 are y-up and drawn upright, 5 have no clear up (the CAD parts
``fandisk`` and ``rocker_arm``, ``fertility``, ``foot``, ``octopus``), and ``horse_48k.ply``,
``nefertiti.obj`` and ``polygirl.off`` are stored z-up, which no bounding-box rule can tell
from a y-up file (the y-up ``horse.off`` has the same extents): they are drawn on their side
unless ``up="z"`` is given. The guess depends on the geometry only, so a render is a function
of its inputs.

**Views** are ``(elevation, azimuth)`` pairs in degrees in the drawing frame of
:func:`frame_axes`, whose first axis (width) is the larger horizontal extent: azimuth -90 looks
at the broad side of the mesh, 0 along its length.
"""

from __future__ import annotations

import numpy as np

from .._common.errors import ParameterError

__all__ = ["UP_AXES", "canonical_frame", "default_views", "direction", "frame_axes", "guess_up"]

#: The accepted values of ``up`` (besides ``None``, the guess).
UP_AXES = ("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z")

_VIEW_PRESETS: dict[int, list[tuple[float, float]]] = {
    1: [(20.0, -130.0)],
    2: [(12.0, -90.0), (20.0, -140.0)],
    3: [(12.0, -90.0), (20.0, -140.0), (20.0, 40.0)],
    4: [(12.0, -90.0), (20.0, -140.0), (20.0, 40.0), (12.0, 90.0)],
}

#: The flat-base test of :func:`guess_up`: normal within arccos(0.98) (11.5 degrees) of the
#: axis, within 2 % of the largest extent from the end, at least 0.5 % of the surface area
#: and four times the flat area at the other end.
_FLAT_COSINE = 0.98
_FLAT_BAND = 0.02
_FLAT_MIN_FRACTION = 0.005
_FLAT_RATIO = 4.0


def parse_up(up: str) -> tuple[int, float]:
    """``(axis, sign)`` of a signed axis name: ``"y"`` is ``(1, 1.0)``, ``"-z"`` ``(2, -1.0)``."""
    if not isinstance(up, str) or up not in UP_AXES:
        raise ParameterError(f"up must be one of {', '.join(UP_AXES[:6])} or None, got {up!r}")
    return "xyz".index(up[-1]), -1.0 if up.startswith("-") else 1.0


def _flat_end_areas(vertices: np.ndarray, faces: np.ndarray, axis: int) -> tuple[float, float]:
    """Fractions of the surface area in faces perpendicular to ``axis`` at its low and its
    high end (see the module docstring)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    doubled = np.linalg.norm(cross, axis=1)
    total = float(doubled.sum())
    if total <= 0.0:
        return 0.0, 0.0
    flat = np.abs(cross[:, axis]) > _FLAT_COSINE * doubled
    height = (a[:, axis] + b[:, axis] + c[:, axis]) / 3.0
    used = vertices[np.unique(faces)]
    band = _FLAT_BAND * float(np.ptp(used, axis=0).max())
    low = flat & (height - used[:, axis].min() <= band)
    high = flat & (used[:, axis].max() - height <= band)
    return float(doubled[low].sum()) / total, float(doubled[high].sum()) / total


def guess_up(vertices: np.ndarray, faces: np.ndarray | None = None) -> str:
    """The signed up axis of a mesh file when none is given (rules in the module docstring).

    Args:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices; without them the sign is always ``+``.

    Returns:
        One of ``"x"``, ``"y"``, ``"z"``, ``"-x"``, ``"-y"``, ``"-z"``.
    """
    extent = np.ptp(vertices, axis=0)
    order = np.argsort(extent, kind="stable")  # smallest first
    axis = 1 if order[0] != 1 else int(order[1])
    name = "xyz"[axis]
    if faces is None or faces.shape[0] == 0:
        return name
    bottom, top = _flat_end_areas(vertices, faces, axis)
    if top >= max(_FLAT_MIN_FRACTION, _FLAT_RATIO * bottom):
        return "-" + name
    return name


def frame_axes(
    vertices: np.ndarray, up: str | None = None, faces: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """The drawing frame ``(width, depth, height)`` of a mesh.

    The height is the ``up`` axis (:func:`guess_up` when ``None``); of the two other axes the
    larger becomes the width and the smaller the depth, so azimuth -90 looks at the largest
    silhouette.

    Args:
        vertices: ``(V, 3)`` positions.
        up: signed axis name or ``None``.
        faces: ``(F, 3)`` faces, used by the guess only.

    Returns:
        ``(3, 3)`` rotation (rows: width, depth, height directions in file coordinates; a
        proper rotation, so orientation is kept), the ``(3,)`` bounding-box centre, and the
        half-size of the cube that contains the mesh.
    """
    axis, sign = parse_up(guess_up(vertices, faces) if up is None else up)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = hi - lo
    others = [a for a in range(3) if a != axis]
    width_axis, depth_axis = sorted(others, key=lambda a: -extent[a])
    rotation = np.zeros((3, 3))
    rotation[0, width_axis] = 1.0
    rotation[1, depth_axis] = 1.0
    rotation[2, axis] = sign
    if np.linalg.det(rotation) < 0:
        rotation[1] = -rotation[1]
    radius = 0.5 * float(extent.max()) or 1.0
    return rotation, 0.5 * (lo + hi), radius


def canonical_frame(
    vertices: np.ndarray, up: str | None = None, faces: np.ndarray | None = None
) -> tuple[np.ndarray, float]:
    """``(V, 3)`` vertices in the drawing frame of :func:`frame_axes`, centred, and the half-size
    of the cube that contains them."""
    rotation, centre, radius = frame_axes(vertices, up, faces)
    return (vertices - centre) @ rotation.T, radius


def direction(elev: float, azim: float) -> np.ndarray:
    """``(3,)`` unit vector towards the camera for matplotlib's ``(elev, azim)`` in degrees."""
    el, az = np.radians(elev), np.radians(azim)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def default_views(count: int = 3) -> list[tuple[float, float]]:
    """Views ``(elevation, azimuth)`` used for ``views=count`` (1 to 4 presets, else a turn)."""
    if count in _VIEW_PRESETS:
        return list(_VIEW_PRESETS[count])
    if count < 1:
        raise ParameterError(f"views must be at least 1, got {count}")
    return [(20.0, -90.0 + 360.0 * i / count) for i in range(count)]


def resolve_views(views) -> list[tuple[float, float]]:
    """A view count or a sequence of ``(elevation, azimuth)`` pairs as a list of pairs."""
    if isinstance(views, int):
        return default_views(views)
    resolved = [(float(e), float(a)) for e, a in views]
    if not resolved:
        raise ParameterError("views must name at least one (elevation, azimuth) pair")
    return resolved

"""Camera and framing: which way is up, the drawing frame of a mesh, and the views.

**Which way is up** (:func:`guess_up`, when ``up`` is not given): the file's ``y`` axis (OBJ,
PLY and glTF), or the middle extent when ``y`` is the smallest; turned over when flat faces at
its top (within 2 % of the largest extent) cover at least 0.5 % of the surface and four times
those at its bottom (scans rest on a base or a planar cut); stood upright when it lies on its
side: the *support* of a signed axis is the convex-hull area of the vertices within 3 % of the
largest extent from its low end, over the bounding box's cross-section; when the chosen axis's
is below 0.1 and another signed axis's (never the smallest extent's) is at least 0.25 and ten
times as much, with the surface's centroid above it, that axis is up.

**Views** are ``(elevation, azimuth)`` pairs in degrees in the drawing frame of
:func:`frame_axes`, whose first axis (width) is the larger horizontal extent: azimuth -90
looks at the broad side. :func:`resolve_views` also takes a count (:func:`default_views`) and
names (:data:`VIEW_NAMES`), alone or in a text such as ``"front,side,top"`` or
``"front,20:-130"`` (``ELEVATION:AZIMUTH``), as ``--views`` does.
"""

from __future__ import annotations

import numpy as np

from .._common.errors import ParameterError
from ._arrays import used_vertices

#: The accepted values of ``up`` (besides ``None``, the guess).
UP_AXES = ("x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z")

#: The views of ``views=1`` and the first ``count`` of ``views=2..4``.
_ONE_VIEW = (20.0, -130.0)
_PRESET_VIEWS = ((12.0, -90.0), (20.0, -140.0), (20.0, 40.0), (12.0, 90.0))

#: The most views one picture takes (each is a panel).
MAX_VIEWS = 12

#: Named views ``(elevation, azimuth)``: straight at a side of the drawing frame (``front`` the
#: broad side, ``side`` = ``right`` the narrow one), or ``iso``, a view from above and between.
VIEW_NAMES: dict[str, tuple[float, float]] = {
    "front": (0.0, -90.0),
    "back": (0.0, 90.0),
    "side": (0.0, 0.0),
    "right": (0.0, 0.0),
    "left": (0.0, 180.0),
    "top": (90.0, -90.0),
    "bottom": (-90.0, -90.0),
    "iso": (20.0, -130.0),
}

#: :func:`guess_up`'s thresholds (module docstring); a face is flat when its normal lies
#: within arccos(0.98) of the axis.
_FLAT_COSINE, _FLAT_BAND, _FLAT_MIN_FRACTION, _FLAT_RATIO = 0.98, 0.02, 0.005, 4.0
_SUPPORT_BAND, _POOR_SUPPORT, _GOOD_SUPPORT, _SUPPORT_RATIO = 0.03, 0.1, 0.25, 10.0


def parse_up(up: str) -> tuple[int, float]:
    """``(axis, sign)`` of a signed axis name: ``"y"`` is ``(1, 1.0)``, ``"-z"`` ``(2, -1.0)``."""
    if not isinstance(up, str) or up not in UP_AXES:
        raise ParameterError(f"up must be one of {', '.join(UP_AXES[:6])} or None, got {up!r}")
    return "xyz".index(up[-1]), -1.0 if up.startswith("-") else 1.0


def _flat_end_areas(vertices: np.ndarray, faces: np.ndarray, axis: int) -> tuple[float, float]:
    """Fractions of the surface area in flat faces at the low and the high end of ``axis``."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    cross = np.cross(b - a, c - a)
    doubled = np.linalg.norm(cross, axis=1)
    total = float(doubled.sum())
    if total <= 0.0:
        return 0.0, 0.0
    flat = np.abs(cross[:, axis]) > _FLAT_COSINE * doubled
    height = (a[:, axis] + b[:, axis] + c[:, axis]) / 3.0
    used = vertices[used_vertices(faces, vertices.shape[0])]
    band = _FLAT_BAND * float(np.ptp(used, axis=0).max())
    low = flat & (height - used[:, axis].min() <= band)
    high = flat & (used[:, axis].max() - height <= band)
    return float(doubled[low].sum()) / total, float(doubled[high].sum()) / total


def support(vertices: np.ndarray, faces: np.ndarray, up: str) -> tuple[float, bool]:
    """The support of ``up`` (the module docstring) for ``(V, 3)`` vertices and ``(F, 3)``
    faces (vertices no face uses are ignored), and whether the surface's centroid lies above
    its hull."""
    from scipy.spatial import ConvexHull, QhullError

    axis, sign = parse_up(up)
    used = vertices[used_vertices(faces, vertices.shape[0])]
    others = [a for a in range(3) if a != axis]
    extent = np.ptp(used, axis=0)
    cross_section = float(extent[others[0]] * extent[others[1]])
    if cross_section <= 0.0:
        return 0.0, False
    height = sign * used[:, axis]
    base = used[height <= height.min() + _SUPPORT_BAND * float(extent.max())][:, others]
    if base.shape[0] < 3:
        return 0.0, False
    try:
        hull = ConvexHull(base)
    except QhullError:  # collinear or coincident points: no area
        return 0.0, False
    planes = hull.equations  # (H, 3) edge half-planes a x + b y + c <= 0
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    weights = np.linalg.norm(np.cross(b - a, c - a), axis=1)
    centres = (a + b + c) / 3.0
    total = float(weights.sum())
    centroid = (weights @ centres) / total if total > 0 else used.mean(axis=0)
    slack = 1e-9 * float(extent.max())
    inside = bool((planes[:, :2] @ centroid[others] + planes[:, 2] <= slack).all())
    return float(hull.volume) / cross_section, inside


def _stood_upright(vertices: np.ndarray, faces: np.ndarray, up: str) -> str:
    """``up``, or the signed axis the mesh stands on when it lies on its side with ``up`` up."""
    current, _ = support(vertices, faces, up)
    if current >= _POOR_SUPPORT:
        return up
    axis = "xyz".index(up[-1])
    # Never the smallest extent: a mesh stood on its broad face would be a plate seen edge-on.
    smallest = int(np.argmin(np.ptp(vertices, axis=0)))
    needed = max(_GOOD_SUPPORT, _SUPPORT_RATIO * current)
    for other in (a for a in range(3) if a not in (axis, smallest)):
        # The file's + direction first: an object also rests well on its flat top.
        for candidate in ("xyz"[other], "-" + "xyz"[other]):
            fraction, centred = support(vertices, faces, candidate)
            if centred and fraction >= needed:
                return candidate
    return up


def guess_up(vertices: np.ndarray, faces: np.ndarray | None = None) -> str:
    """The signed up axis (``"x"`` ... ``"-z"``) of ``(V, 3)`` vertices when none is given
    (the module docstring); without ``(F, 3)`` faces only the axis is guessed, sign ``+``."""
    extent = np.ptp(vertices, axis=0)
    order = np.argsort(extent, kind="stable")  # smallest first
    axis = 1 if order[0] != 1 else int(order[1])
    name = "xyz"[axis]
    if faces is None or faces.shape[0] == 0:
        return name
    bottom, top = _flat_end_areas(vertices, faces, axis)
    if top >= max(_FLAT_MIN_FRACTION, _FLAT_RATIO * bottom):
        name = "-" + name
    return _stood_upright(vertices, faces, name)


def frame_axes(
    vertices: np.ndarray, up: str | None = None, faces: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """The drawing frame ``(width, depth, height)`` of ``(V, 3)`` vertices: the height is
    ``up`` (:func:`guess_up` from ``faces`` when ``None``), the width the larger other extent
    (azimuth -90 looks at the largest silhouette).

    Returns:
        The ``(3, 3)`` proper rotation (rows: width, depth, height in file coordinates), the
        ``(3,)`` bounding-box centre, and the half-size of the cube that holds the mesh.
    """
    axis, sign = parse_up(guess_up(vertices, faces) if up is None else up)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = hi - lo
    others = [a for a in range(3) if a != axis]
    width_axis, depth_axis = sorted(others, key=lambda a: -extent[a])
    rotation = np.eye(3)[[width_axis, depth_axis, axis]] * [[1.0], [1.0], [sign]]
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


def screen_axes(elev: float, azim: float) -> np.ndarray:
    """``(3, 3)`` rows: the unit vectors of the picture's right, its up and the direction
    towards the camera, for a view ``(elev, azim)`` in degrees (matplotlib's convention: the
    drawing frame's third axis points up in the picture). ``points @ screen_axes(...).T`` gives
    each point's ``(x, y, depth)`` in an orthographic view, nearer points deeper."""
    el, az = np.radians(elev), np.radians(azim)
    right = np.array([-np.sin(az), np.cos(az), 0.0])
    up = np.array([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)])
    return np.stack([right, up, direction(elev, azim)])


def default_views(count: int = 3) -> list[tuple[float, float]]:
    """Views ``(elevation, azimuth)`` used for ``views=count`` (1 to 4 presets, else a turn)."""
    if count < 1:
        raise ParameterError(f"views must be at least 1, got {count}")
    if count <= len(_PRESET_VIEWS):
        return [_ONE_VIEW] if count == 1 else list(_PRESET_VIEWS[:count])
    return [(20.0, -90.0 + 360.0 * i / count) for i in range(count)]


def _view(item) -> tuple[float, float]:
    """A name of :data:`VIEW_NAMES`, ``"ELEVATION:AZIMUTH"`` or a pair as a checked
    ``(elevation, azimuth)``: finite, the elevation within ``[-90, 90]``."""
    if isinstance(item, str):
        name = item.strip().lower()
        try:
            return VIEW_NAMES.get(name) or _view(tuple(float(x) for x in name.split(":")))
        except ValueError:  # not a pair of numbers, or not a view: reported with the names
            raise ParameterError(
                f"unknown view {item.strip()!r}: use {', '.join(VIEW_NAMES)} or "
                "ELEVATION:AZIMUTH in degrees (e.g. 20:-130)"
            ) from None
    if np.ndim(item) != 1 or len(item) != 2:
        raise ParameterError(f"a view must be a name or an (elevation, azimuth) pair: {item!r}")
    try:
        elev, azim = float(item[0]), float(item[1])
    except (TypeError, ValueError):
        raise ParameterError(f"a view must be two numbers, got {tuple(item)!r}") from None
    if not (np.isfinite(elev) and np.isfinite(azim) and -90.0 <= elev <= 90.0):
        raise ParameterError(
            f"a view needs a finite elevation in [-90, 90] and a finite azimuth, "
            f"got ({elev}, {azim})"
        )
    return elev, azim


def resolve_views(views) -> list[tuple[float, float]]:
    """``views`` (module docstring: a count, a text, or a sequence of names and pairs) as
    ``(elevation, azimuth)`` pairs, at most ``MAX_VIEWS``; else :class:`ParameterError` (as
    for no view, an unknown name, or an elevation outside ``[-90, 90]``)."""
    if isinstance(views, str) and views.strip().isdigit():
        views = int(views)
    if isinstance(views, (int, np.integer)) and not isinstance(views, bool):
        _at_most_max(views)  # before the views are built: 10**20 would fill the memory
        return default_views(int(views))
    if isinstance(views, str):
        views = [part for part in views.split(",") if part.strip()]
    try:
        resolved = [_view(item) for item in views]
    except TypeError:
        raise ParameterError(f"views must be a count, names or pairs, got {views!r}") from None
    if not resolved:
        raise ParameterError("views must name at least one view")
    _at_most_max(len(resolved))
    return resolved


def _at_most_max(count: int) -> None:
    if count > MAX_VIEWS:
        raise ParameterError(f"at most {MAX_VIEWS} views fit a picture, got {count}")

"""Pictures of meshes and per-vertex scalar fields (saliency, multiscale strips, interest points).

matplotlib is an optional dependency (``pip install "stochlap_torch[viz]"``); it is imported
only inside the functions here. Figures are drawn on matplotlib's Agg canvas directly, without
pyplot, so nothing here changes the caller's backend or opens a window.

Every function takes array-likes (numpy arrays or torch tensors): ``vertices`` ``(V, 3)``,
``faces`` ``(F, 3)`` and per-vertex ``values`` ``(V,)``. Meshes are drawn with a
``Poly3DCollection`` per view (matplotlib sorts its triangles far to near), orthographic
projection, equal aspect, two-sided Lambert shading from a light above and left of the camera
(smooth, from vertex normals, when the faces are consistently oriented), and back faces culled
when the mesh is closed. The vertical axis and the viewing directions come from the bounding
box (see :func:`_frame_axes` and :func:`default_views`), each view is zoomed to fit, and the
figure is drawn at three times the resolution and filtered down for clean anti-aliasing.
"""

from __future__ import annotations

import io
import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = [
    "default_views",
    "render_interest_points",
    "render_multiscale",
    "render_scalar",
    "robust_range",
    "scalar_colors",
]

logger = logging.getLogger(__name__)

#: Views as ``(elevation, azimuth)`` in degrees, in the canonical frame of
#: :func:`_canonical_frame`: azimuth -90 looks at the broad side of the mesh (its two largest
#: bounding-box extents fill the picture), 0 looks along its length.
_VIEW_PRESETS: dict[int, list[tuple[float, float]]] = {
    1: [(20.0, -130.0)],
    2: [(12.0, -90.0), (20.0, -140.0)],
    3: [(12.0, -90.0), (20.0, -140.0), (20.0, 40.0)],
    4: [(12.0, -90.0), (20.0, -140.0), (20.0, 40.0), (12.0, 90.0)],
}

_AXES = {"x": 0, "y": 1, "z": 2}

#: Inches below the mesh panels kept for the colour bar, and the bar's distance from the bottom.
_BAR_SPACE = 0.95
_BAR_BOTTOM = 0.5

#: Figures are drawn this many times larger and filtered down (anti-aliasing of the meshes).
_SUPERSAMPLE = 3
_MAX_DRAW_PIXELS = 40_000_000


def _mpl():
    """Import matplotlib (and register the 3D projection), or explain how to install it."""
    try:
        import matplotlib
        from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
        from mpl_toolkits.mplot3d import Axes3D  # noqa: F401  (registers projection="3d")
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise ImportError(
            'stochlap_torch.render needs matplotlib: pip install "stochlap_torch[viz]"'
        ) from exc
    return matplotlib


def _numpy(array, dtype=None) -> np.ndarray:
    """A numpy copy-free view of a tensor or array-like."""
    if hasattr(array, "detach"):
        array = array.detach().cpu().numpy()
    return np.asarray(array, dtype=dtype)


def _check_mesh(vertices, faces) -> tuple[np.ndarray, np.ndarray]:
    vertices = _numpy(vertices, np.float64)
    faces = _numpy(faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape (V, 3), got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
        raise ValueError(f"faces must have shape (F, 3) with F > 0, got {faces.shape}")
    faces = faces.astype(np.int64, copy=False)
    if faces.min() < 0 or faces.max() >= vertices.shape[0]:
        raise ValueError(f"face indices must lie in [0, {vertices.shape[0]})")
    return vertices, faces


def _check_values(values, num_vertices: int, name: str = "values") -> np.ndarray:
    values = _numpy(values, np.float64).reshape(-1)
    if values.shape[0] != num_vertices:
        raise ValueError(
            f"{name} must have one entry per vertex ({num_vertices}), got {values.shape}"
        )
    return values


# --------------------------------------------------------------------------------------------
# Colours


def robust_range(
    values,
    faces=None,
    vmin: float | None = None,
    vmax: float | None = None,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> tuple[float, float]:
    """The colour range for a per-vertex scalar: by default its 1st and 99th percentiles.

    Args:
        values: ``(V,)`` scalars.
        faces: optional ``(F, 3)`` faces; when given, only vertices some face uses count
            (unreferenced vertices are invisible but can carry extreme values, e.g. the lowest
            saliency, and would otherwise stretch the range).
        vmin, vmax: fixed bounds, kept as given.
        percentiles: the percentiles used for a bound that is not given.

    Returns:
        ``(vmin, vmax)`` with ``vmin < vmax``: a constant field gets a tiny range around its
        value, so that it maps to the middle of the colormap.
    """
    values = _numpy(values, np.float64).reshape(-1)
    if faces is not None:
        values = values[np.unique(_numpy(faces).astype(np.int64))]
    finite = values[np.isfinite(values)]
    if vmin is None or vmax is None:
        if finite.size:
            lo, hi = np.percentile(finite, percentiles)
        else:
            lo, hi = 0.0, 1.0
        vmin = float(lo) if vmin is None else float(vmin)
        vmax = float(hi) if vmax is None else float(vmax)
    if not vmax > vmin:  # constant field (or inverted bounds): a tiny range around the value
        centre = 0.5 * (vmin + vmax)
        half = 0.5 * max(abs(centre) * 1e-6, 1e-12) if np.isfinite(centre) else 0.5
        if not np.isfinite(centre):
            centre = 0.0
        vmin, vmax = centre - half, centre + half
    return float(vmin), float(vmax)


def _normalise(values: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Map to ``[0, 1]`` (clipped); non-finite values stay NaN."""
    with np.errstate(invalid="ignore"):
        return np.clip((values - vmin) / (vmax - vmin), 0.0, 1.0)


#: matplotlib's "inferno" sampled at 17 evenly spaced points, so that :func:`scalar_colors`
#: (PLY vertex colours) works without matplotlib for the default colormap.
_INFERNO_17 = np.array(
    [
        [0, 0, 4], [11, 7, 36], [33, 12, 74], [61, 9, 101], [87, 16, 110], [113, 25, 110],
        [138, 34, 106], [163, 44, 97], [188, 55, 84], [210, 70, 68], [228, 90, 49],
        [241, 115, 29], [249, 142, 9], [252, 172, 17], [249, 203, 53], [242, 234, 105],
        [252, 255, 164],
    ],
    dtype=np.float64,
)  # fmt: skip


def _colormap(cmap):
    matplotlib = _mpl()
    return matplotlib.colormaps[cmap] if isinstance(cmap, str) else cmap


def _map_colors(unit: np.ndarray, cmap) -> np.ndarray:
    """``(N, 4)`` float RGBA in ``[0, 1]`` for values in ``[0, 1]`` (NaN-free)."""
    try:
        return np.asarray(_colormap(cmap)(unit), dtype=np.float64)
    except ImportError:
        if cmap != "inferno":
            raise
    knots = np.linspace(0.0, 1.0, _INFERNO_17.shape[0])
    rgb = np.stack([np.interp(unit, knots, _INFERNO_17[:, i]) for i in range(3)], axis=1)
    return np.concatenate([rgb / 255.0, np.ones((unit.shape[0], 1))], axis=1)


def scalar_colors(
    values, cmap: str = "inferno", vmin: float | None = None, vmax: float | None = None
) -> np.ndarray:
    """Per-vertex colours for a scalar field, e.g. for the vertex colours of a PLY file.

    Args:
        values: ``(V,)`` scalars (numpy array or tensor).
        cmap: a matplotlib colormap name or object. The default, ``"inferno"``, also works
            without matplotlib installed.
        vmin, vmax: the range mapped onto the colormap; by default the 1st and 99th
            percentiles of the finite values (:func:`robust_range`), so that a few extreme
            vertices do not wash out the rest. A constant field gets the middle colour.

    Returns:
        ``(V, 4)`` uint8 RGBA array. Non-finite values are mid grey.
    """
    values = _numpy(values, np.float64).reshape(-1)
    lo, hi = robust_range(values, vmin=vmin, vmax=vmax)
    unit = _normalise(values, lo, hi)
    finite = np.isfinite(unit)
    rgba = _map_colors(np.where(finite, unit, 0.0), cmap)
    rgba[~finite] = (0.5, 0.5, 0.5, 1.0)
    return np.round(rgba * 255.0).astype(np.uint8)


# --------------------------------------------------------------------------------------------
# Geometry helpers


def _frame_axes(
    vertices: np.ndarray, up: str | None = None
) -> tuple[np.ndarray, np.ndarray, float]:
    """Choose the drawing frame ``(width, depth, height)`` of a mesh from its bounding box.

    The vertical axis is ``up`` if given (``"x"``, ``"y"`` or ``"z"``), else the file's ``y``
    axis (the OBJ/PLY/glTF convention) unless ``y`` is the smallest extent, in which case the
    middle extent (so a flat mesh lies flat). Of the two other axes the larger becomes the
    width and the smaller the depth, so azimuth -90 looks at the largest silhouette.

    Returns:
        ``(3, 3)`` rotation (rows: width, depth, height directions in file coordinates, a
        proper rotation so that orientation is kept), the ``(3,)`` bounding-box centre, and
        the half-size of the cube that contains the mesh.
    """
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    extent = hi - lo
    if up is None:
        order = np.argsort(extent, kind="stable")  # smallest first
        up_axis = 1 if order[0] != 1 else int(order[1])
    else:
        if up not in _AXES:
            raise ValueError(f"up must be one of 'x', 'y', 'z' or None, got {up!r}")
        up_axis = _AXES[up]
    others = [a for a in range(3) if a != up_axis]
    width_axis, depth_axis = sorted(others, key=lambda a: -extent[a])
    rotation = np.zeros((3, 3))
    rotation[0, width_axis] = rotation[1, depth_axis] = rotation[2, up_axis] = 1.0
    if np.linalg.det(rotation) < 0:
        rotation[1] = -rotation[1]
    radius = 0.5 * float(extent.max()) or 1.0
    return rotation, 0.5 * (lo + hi), radius


def _canonical_frame(vertices: np.ndarray, up: str | None = None) -> tuple[np.ndarray, float]:
    """Vertices in the drawing frame of :func:`_frame_axes`, centred, and the cube half-size."""
    rotation, centre, radius = _frame_axes(vertices, up)
    return (vertices - centre) @ rotation.T, radius


class _Geometry:
    """What shading needs of a mesh in its drawing frame, computed once for all views.

    Attributes:
        face_normals: ``(F, 3)`` unit normals (zero for degenerate faces).
        vertex_normals: ``(V, 3)`` area-weighted unit normals for smooth shading, or ``None``
            when the faces are not consistently oriented (normals would cancel).
        outward: +1 or -1 if the mesh is closed and consistently oriented with outward or
            inward normals (back faces can then be culled), else 0.
    """

    def __init__(self, frame: np.ndarray, faces: np.ndarray):
        a, b, c = (frame[faces[:, i]] for i in range(3))
        area_normals = np.cross(b - a, c - a)
        self.face_normals = _unit(area_normals)
        directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        num_vertices = int(frame.shape[0])
        keys = directed[:, 0] * num_vertices + directed[:, 1]
        unique_keys = np.unique(keys)
        # A directed edge used twice means two neighbouring faces disagree on orientation.
        consistent = unique_keys.size == keys.size
        self.vertex_normals = None
        self.outward = 0.0
        if consistent:
            summed = np.zeros_like(frame)
            for i in range(3):
                np.add.at(summed, faces[:, i], area_normals)
            self.vertex_normals = _unit(summed)
            reverse = directed[:, 1] * num_vertices + directed[:, 0]
            if np.isin(reverse, unique_keys).all():  # no boundary edge: closed
                volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum())
                self.outward = float(np.sign(volume))

    def shade(self, faces: np.ndarray, keep: np.ndarray, elev: float, azim: float) -> np.ndarray:
        """``(len(keep),)`` shading factors of the faces ``keep`` seen from ``(elev, azim)``.

        Two-sided Lambert shading with a light above and to the left of the camera, evaluated
        at the vertices and averaged over each face when vertex normals exist (smooth), per
        face otherwise (flat).
        """
        ambient = 0.28
        light = _direction(elev + 30.0, azim - 35.0)
        if self.vertex_normals is not None:
            lambert = np.abs(self.vertex_normals @ light)[faces[keep]].mean(axis=1)
        else:
            lambert = np.abs(self.face_normals[keep] @ light)
        return ambient + (1.0 - ambient) * lambert


def _unit(vectors: np.ndarray) -> np.ndarray:
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, norms, out=np.zeros_like(vectors), where=norms > 0)


def _direction(elev: float, azim: float) -> np.ndarray:
    """Unit vector towards the camera for matplotlib's ``(elev, azim)``."""
    el, az = np.radians(elev), np.radians(azim)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def default_views(count: int = 3) -> list[tuple[float, float]]:
    """Views ``(elevation, azimuth)`` used for ``views=count`` (1 to 4 presets, else a turn)."""
    if count in _VIEW_PRESETS:
        return list(_VIEW_PRESETS[count])
    if count < 1:
        raise ValueError(f"views must be at least 1, got {count}")
    return [(20.0, -90.0 + 360.0 * i / count) for i in range(count)]


def _resolve_views(views) -> list[tuple[float, float]]:
    if isinstance(views, int):
        return default_views(views)
    resolved = [(float(e), float(a)) for e, a in views]
    if not resolved:
        raise ValueError("views must name at least one (elevation, azimuth) pair")
    return resolved


# --------------------------------------------------------------------------------------------
# Drawing


def _new_figure(figsize: tuple[float, float], dpi: float):
    _mpl()
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=figsize, dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    return fig


def _mesh_axes(
    fig, rect, frame: np.ndarray, radius: float, elev: float, azim: float, fill: float = 0.94
):
    """A bare orthographic 3D axes on the cube ``[-radius, radius]^3``, zoomed so that the
    ``(V, 3)`` points ``frame`` fill the fraction ``fill`` of the panel seen from the view."""
    from mpl_toolkits.mplot3d import proj3d

    ax = fig.add_axes(rect, projection="3d")
    ax.set_proj_type("ortho")
    ax.view_init(elev=elev, azim=azim)
    for setter in (ax.set_xlim, ax.set_ylim, ax.set_zlim):
        setter(-radius, radius)
    ax.set_box_aspect((1.0, 1.0, 1.0), zoom=1.0)
    ax.set_axis_off()
    ax.computed_zorder = False
    # The projection is known before drawing: measure the mesh at zoom 1 and scale to fit.
    xs, ys, _ = proj3d.proj_transform(frame[:, 0], frame[:, 1], frame[:, 2], ax.get_proj())
    pixels = ax.transData.transform(np.column_stack([xs, ys]))
    x0, y0, width, height = ax.bbox.bounds
    reach_x = np.abs(pixels[:, 0] - (x0 + width / 2)).max()
    reach_y = np.abs(pixels[:, 1] - (y0 + height / 2)).max()
    if np.isfinite(reach_x) and np.isfinite(reach_y) and max(reach_x, reach_y) > 0:
        zoom = fill * min(width / 2 / max(reach_x, 1e-9), height / 2 / max(reach_y, 1e-9))
        ax.set_box_aspect((1.0, 1.0, 1.0), zoom=float(np.clip(zoom, 0.1, 10.0)))
    return ax


def _draw_mesh(ax, frame, faces, geometry: _Geometry, face_rgb, elev, azim):
    """Add one shaded ``Poly3DCollection`` of the faces visible from ``(elev, azim)``."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    if geometry.outward != 0.0:
        facing = geometry.outward * (geometry.face_normals @ _direction(elev, azim))
        keep = np.flatnonzero(facing > -1e-9)
    else:
        keep = np.arange(faces.shape[0])
    shade = geometry.shade(faces, keep, elev, azim)
    rgb = np.clip(face_rgb[keep] * shade[:, None], 0.0, 1.0)
    polygons = frame[faces[keep]]
    # matplotlib sorts the polygons far to near by mean depth at draw time (painter's order).
    collection = Poly3DCollection(
        polygons,
        facecolors=rgb,
        edgecolors="none",
        linewidths=0.0,
        # Anti-aliased triangles leave seams that let the background and hidden faces show
        # through; _save supersamples the whole figure instead.
        antialiased=False,
        zsort="average",
    )
    collection.set_zorder(1)
    ax.add_collection3d(collection)
    return collection


def _face_values(values: np.ndarray, faces: np.ndarray) -> np.ndarray:
    return values[faces].mean(axis=1)


def _add_colorbar(fig, rect, cmap, vmin: float, vmax: float, label: str | None):
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.ticker import MaxNLocator

    cax = fig.add_axes(rect)
    mappable = ScalarMappable(norm=Normalize(vmin=vmin, vmax=vmax), cmap=_colormap(cmap))
    # "extend" arrows: values beyond the robust range are clipped to the end colours.
    bar = fig.colorbar(mappable, cax=cax, orientation="horizontal", extend="both")
    if label:
        bar.set_label(label, fontsize=10)
    width_inches = rect[2] * fig.get_size_inches()[0]
    bar.locator = MaxNLocator(nbins=max(3, int(width_inches * 2.2)))
    bar.update_ticks()
    bar.ax.tick_params(labelsize=8)
    return bar


def _panel_rects(count: int, bottom: float, top: float) -> list[list[float]]:
    width = 1.0 / count
    return [[i * width, bottom, width, top - bottom] for i in range(count)]


def _finish(fig, figsize, cmap, lo, hi, label, title, path):
    """Add the centred colour bar and the title, then write the figure."""
    bar_width = min(0.6, 3.6 / figsize[0])
    _add_colorbar(
        fig,
        [0.5 - bar_width / 2, _BAR_BOTTOM / figsize[1], bar_width, 0.16 / figsize[1]],
        cmap,
        lo,
        hi,
        label,
    )
    if title:
        fig.suptitle(title, fontsize=13, y=1.0 - 0.08 / figsize[1], va="top")
    return _save(fig, path)


def _save(fig, path, supersample: int = _SUPERSAMPLE) -> Path:
    """Write ``fig`` as a PNG of ``figsize * dpi`` pixels, drawn ``supersample`` times larger
    and box-filtered down so that the (non anti-aliased) mesh edges come out smooth."""
    from PIL import Image  # a dependency of matplotlib

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    width, height = (round(x * fig.dpi) for x in fig.get_size_inches())
    # Keep the large intermediate image within about 40 million pixels.
    supersample = max(1, min(supersample, int((_MAX_DRAW_PIXELS / (width * height)) ** 0.5)))
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=fig.dpi * supersample, facecolor="white")
    buffer.seek(0)
    with Image.open(buffer) as image:
        image.convert("RGB").resize((width, height), Image.Resampling.BOX).save(path, "PNG")
    logger.info("wrote %s", path)
    return path


def render_scalar(
    vertices,
    faces,
    values,
    path,
    *,
    views: int | Sequence[tuple[float, float]] = 3,
    cmap: str = "inferno",
    title: str | None = None,
    label: str | None = "saliency",
    vmin: float | None = None,
    vmax: float | None = None,
    up: str | None = None,
    figsize: tuple[float, float] | None = None,
    dpi: float = 100,
) -> Path:
    """Draw a mesh coloured by a per-vertex scalar from a few views, with a colour bar.

    Each face gets the mean of its three vertex values; colours span
    :func:`robust_range` of the vertices the faces use unless ``vmin``/``vmax`` are given.

    Args:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.
        values: ``(V,)`` scalar per vertex.
        path: output PNG file (parent folders are created).
        views: number of views (see :func:`default_views`) or ``(elevation, azimuth)`` pairs
            in the mesh's canonical frame.
        cmap: matplotlib colormap name.
        title: optional figure title.
        label: colour bar label.
        vmin, vmax: colour range.
        up: vertical axis of the mesh file (``"x"``, ``"y"``, ``"z"``), or ``None`` to guess.
        figsize: figure size in inches, default ``(4 * views, 4.8)`` (``5.2`` with a title).
        dpi: pixels per inch; the PNG is ``figsize * dpi`` pixels.

    Returns:
        The path written.
    """
    vertices, faces = _check_mesh(vertices, faces)
    values = _check_values(values, vertices.shape[0])
    view_list = _resolve_views(views)
    lo, hi = robust_range(values, faces, vmin=vmin, vmax=vmax)
    if figsize is None:
        figsize = (4.0 * len(view_list), 5.2 if title else 4.8)

    frame, radius = _canonical_frame(vertices, up)
    geometry = _Geometry(frame, faces)
    unit = _normalise(_face_values(values, faces), lo, hi)
    face_rgb = _colormap(cmap)(np.nan_to_num(unit, nan=0.5))[:, :3]
    face_rgb[~np.isfinite(unit)] = 0.5

    fig = _new_figure(figsize, dpi)
    bottom = _BAR_SPACE / figsize[1]  # inches to figure fraction
    top = 1.0 - (0.45 / figsize[1] if title else 0.0)
    for rect, (elev, azim) in zip(
        _panel_rects(len(view_list), bottom, top), view_list, strict=True
    ):
        ax = _mesh_axes(fig, rect, frame, radius, elev, azim)
        _draw_mesh(ax, frame, faces, geometry, face_rgb, elev, azim)
    return _finish(fig, figsize, cmap, lo, hi, label, title, path)


def _default_scales(num_scales: int, count: int = 5) -> list[int]:
    return sorted({round(float(x)) for x in np.linspace(0, num_scales - 1, min(count, num_scales))})


def render_multiscale(
    positions,
    faces,
    path,
    scales: Sequence[int] | None = None,
    *,
    view: tuple[float, float] = (20.0, -55.0),
    up: str | None = None,
    first_scale: int = 1,
    title: str | None = None,
    figsize: tuple[float, float] | None = None,
    dpi: float = 100,
) -> Path:
    """Draw a strip of the mesh at several scales of a multiscale representation, grey shaded.

    Args:
        positions: ``(K, V, 3)`` vertex positions per scale (``positions[0]`` the input mesh).
        faces: ``(F, 3)`` vertex indices, shared by all scales.
        path: output PNG file.
        scales: 0-based indices into ``positions`` to show; default about 5 evenly spaced,
            first and last included.
        view: ``(elevation, azimuth)`` in the canonical frame of ``positions[0]``.
        up: vertical axis of the mesh file, or ``None`` to guess.
        first_scale: number of the scale ``positions[0]`` in the panel titles (the paper
            numbers scales from 1, so panel ``i`` is titled ``k=i+1``).
        title: optional figure title.
        figsize: default ``(3.2 * panels, 3.6)`` inches (``4.0`` with a title).
        dpi: pixels per inch.

    Returns:
        The path written.
    """
    positions = _numpy(positions, np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] == 0:
        raise ValueError(f"positions must have shape (K, V, 3), got {positions.shape}")
    _, faces = _check_mesh(positions[0], faces)
    num_scales = positions.shape[0]
    chosen = _default_scales(num_scales) if scales is None else [int(s) for s in scales]
    if not chosen or min(chosen) < -num_scales or max(chosen) >= num_scales:
        raise ValueError(f"scales must be indices into {num_scales} scales, got {chosen}")
    chosen = [s % num_scales for s in chosen]
    if figsize is None:
        figsize = (3.2 * len(chosen), 4.0 if title else 3.6)

    # One frame for all panels, from the input mesh, so that shrinking is visible.
    rotation, centre, radius = _frame_axes(positions[0], up)
    first_frame = (positions[0] - centre) @ rotation.T
    grey = np.full((faces.shape[0], 3), 0.82)
    fig = _new_figure(figsize, dpi)
    top = 1.0 - (0.45 / figsize[1] if title else 0.0)
    label_height = 0.35 / figsize[1]
    elev, azim = view
    for rect, index in zip(_panel_rects(len(chosen), 0.0, top - label_height), chosen, strict=True):
        frame = (positions[index] - centre) @ rotation.T
        ax = _mesh_axes(fig, rect, first_frame, radius, elev, azim)
        _draw_mesh(ax, frame, faces, _Geometry(frame, faces), grey, elev, azim)
        fig.text(
            rect[0] + rect[2] / 2,
            top - label_height / 2,
            f"k={index + first_scale}",
            ha="center",
            va="center",
            fontsize=12,
        )
    if title:
        fig.suptitle(title, fontsize=13, y=1.0 - 0.08 / figsize[1], va="top")
    return _save(fig, path)


def _visible(
    frame: np.ndarray, faces: np.ndarray, points: np.ndarray, direction: np.ndarray
) -> np.ndarray:
    """Which of the ``(N, 3)`` points no triangle hides from a camera at infinity along
    ``direction`` (a Moller-Trumbore ray test per point, in chunks of faces)."""
    if points.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    scale = float(np.ptp(frame, axis=0).max()) or 1.0
    origins = points + 1e-4 * scale * direction
    a, b, c = (frame[faces[:, i]] for i in range(3))
    edge1, edge2 = b - a, c - a
    hidden = np.zeros(points.shape[0], dtype=bool)
    pvec = np.cross(direction, edge2)  # (F, 3)
    det = np.einsum("ij,ij->i", edge1, pvec)
    usable = np.abs(det) > 1e-14 * scale * scale
    edge1, edge2, a, pvec, det = edge1[usable], edge2[usable], a[usable], pvec[usable], det[usable]
    inv_det = 1.0 / det
    chunk = max(1, 2_000_000 // max(1, a.shape[0]))
    for start in range(0, points.shape[0], chunk):
        origin = origins[start : start + chunk, None, :]  # (n, 1, 3)
        tvec = origin - a[None]  # (n, F, 3)
        u = np.einsum("nfi,fi->nf", tvec, pvec) * inv_det
        qvec = np.cross(tvec, edge1[None])
        v = np.einsum("i,nfi->nf", direction, qvec) * inv_det
        t = np.einsum("fi,nfi->nf", edge2, qvec) * inv_det
        hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        hidden[start : start + chunk] = hit.any(axis=1)
    return ~hidden


def render_interest_points(
    vertices,
    faces,
    saliency,
    points,
    path,
    *,
    views: int | Sequence[tuple[float, float]] = 3,
    cmap: str = "inferno",
    title: str | None = None,
    label: str | None = "saliency",
    up: str | None = None,
    marker_color: str = "#19e6ff",
    figsize: tuple[float, float] | None = None,
    dpi: float = 100,
) -> Path:
    """Draw a mesh coloured by saliency with interest points as large markers, a few views.

    In each view only the points that no part of the mesh hides are drawn.

    Args:
        vertices: ``(V, 3)`` positions.
        faces: ``(F, 3)`` vertex indices.
        saliency: ``(V,)`` saliency per vertex.
        points: ``(N,)`` vertex indices of the interest points.
        path: output PNG file.
        views, cmap, title, label, up, figsize, dpi: as for :func:`render_scalar`.
        marker_color: fill colour of the markers.

    Returns:
        The path written.
    """
    vertices, faces = _check_mesh(vertices, faces)
    saliency = _check_values(saliency, vertices.shape[0], "saliency")
    points = _numpy(points).astype(np.int64).reshape(-1)
    if points.size and (points.min() < 0 or points.max() >= vertices.shape[0]):
        raise ValueError(f"points must be vertex indices in [0, {vertices.shape[0]})")
    view_list = _resolve_views(views)
    lo, hi = robust_range(saliency, faces)
    if figsize is None:
        figsize = (4.0 * len(view_list), 5.2 if title else 4.8)

    frame, radius = _canonical_frame(vertices, up)
    geometry = _Geometry(frame, faces)
    unit = _normalise(_face_values(saliency, faces), lo, hi)
    face_rgb = _colormap(cmap)(np.nan_to_num(unit, nan=0.5))[:, :3]
    face_rgb[~np.isfinite(unit)] = 0.5
    point_xyz = frame[points]
    marker_size = float(np.clip(2400.0 / max(points.size, 1), 30.0, 110.0))

    fig = _new_figure(figsize, dpi)
    bottom = _BAR_SPACE / figsize[1]
    top = 1.0 - (0.45 / figsize[1] if title else 0.0)
    for rect, (elev, azim) in zip(
        _panel_rects(len(view_list), bottom, top), view_list, strict=True
    ):
        ax = _mesh_axes(fig, rect, frame, radius, elev, azim)
        _draw_mesh(ax, frame, faces, geometry, face_rgb, elev, azim)
        visible = _visible(frame, faces, point_xyz, _direction(elev, azim))
        shown = point_xyz[visible]
        if shown.size:
            # Nudge towards the camera so the markers sit on the surface, not in it.
            shown = shown + 0.01 * radius * _direction(elev, azim)
            ax.scatter(
                shown[:, 0],
                shown[:, 1],
                shown[:, 2],
                s=marker_size,
                c=marker_color,
                edgecolors="black",
                linewidths=1.2,
                depthshade=False,
                zorder=2,
            )
        fig.text(
            rect[0] + rect[2] / 2,
            bottom - 0.06 / figsize[1],
            f"{int(visible.sum())} of {points.size} points visible",
            ha="center",
            va="top",
            fontsize=8,
            color="0.35",
        )
    return _finish(fig, figsize, cmap, lo, hi, label, title, path)

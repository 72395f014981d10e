"""The figures: a mesh coloured by a scalar, a multiscale strip, interest points, and the
interest-point error curves (FNE, FPE and WME against the localisation radius, Fig. 15).

Each takes array-likes (numpy arrays or tensors) and writes one PNG file atomically; meshes
are drawn orthographically in the drawing frame of :mod:`~stochlap_torch.viz.framing`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .._common.checks import check_optional_int
from .._common.errors import ParameterError
from ._arrays import as_numpy, check_dpi, check_mesh, check_values
from .backend import new_figure, save_figure
from .colors import check_cmap, face_colors, robust_range, value_span, vertex_colors
from .decimate import DRAW_FACES, drawing_faces, nearest_drawn
from .drawing import (
    BAR_SPACE,
    TITLE_SPACE,
    add_title,
    draw_mesh,
    finish_with_colorbar,
    grid_rects,
    mesh_axes,
    panel_rects,
)
from .framing import canonical_frame, direction, frame_axes, resolve_views, screen_axes
from .shading import Geometry, visible_points


def render_scalar(
    vertices,
    faces,
    values,
    path,
    *,
    views: int | str | Sequence = 3,
    cmap: str = "inferno",
    title: str | None = None,
    label: str | None = "saliency",
    vmin: float | None = None,
    vmax: float | None = None,
    up: str | None = None,
    figsize: tuple[float, float] | None = None,
    dpi: float = 100,
    points=None,
    marker_color: str = "#19e6ff",
    max_faces: int | None = DRAW_FACES,
    shading: str = "smooth",
) -> Path:
    """Draw a mesh coloured by a per-vertex scalar from a few views, with a colour bar, and
    optionally vertices (interest points) as markers.

    Colours are interpolated across each face from its corners' values (``shading="smooth"``)
    or each face gets the mean of its three vertex values (``"flat"``); colours span
    :func:`~stochlap_torch.viz.robust_range` of the vertices the faces use unless
    ``vmin``/``vmax`` are given, and the colour bar marks an end that clips values (an arrow,
    and their true extreme). Each view draws only the points no part of the mesh hides.

    Args:
        vertices, faces, values: ``(V, 3)`` positions, ``(F, 3)`` indices, ``(V,)`` scalars.
        path: output PNG file (parent folders are created); returned.
        views: a count (:func:`~stochlap_torch.viz.default_views`), names and ``(elevation,
            azimuth)`` pairs in the drawing frame, or a text such as ``"front,side,top"``.
        cmap, label: colormap (name or object) and colour bar label (``None``: no label).
        vmin, vmax: colour range (``None``: the 1st / 99th percentile of the faces' vertices).
        title: figure title (``None``: none, and no room kept for it).
        up: vertical axis of the mesh file (``"x"`` ... ``"-z"``; ``None``: guessed,
            :func:`~stochlap_torch.viz.guess_up`).
        figsize: inches, default ``(4 * views, 4.8)`` (``5.2`` with a title).
        dpi: pixels per inch (10 to 600); the PNG is ``figsize * dpi`` pixels.
        points, marker_color: ``(N,)`` vertex indices to mark (``None``: none), and the markers'
            colour.
        max_faces: a mesh with more faces is drawn from a decimated copy of about this many
            (:mod:`~stochlap_torch.viz.decimate`; ``None``: every face); colours, their range
            and the markers come from the full mesh.
        shading: ``"smooth"`` (colours and light interpolated across each face from its
            corners) or ``"flat"`` (one colour per face).

    Raises:
        MeshError, ParameterError: bad mesh, values, points, views, colormap, dpi, budget or
            shading.
    """
    vertices, faces = check_mesh(vertices, faces)
    values = check_values(values, vertices.shape[0])
    if points is not None:
        points = as_numpy(points).astype(np.int64).reshape(-1)
        if points.size and (points.min() < 0 or points.max() >= vertices.shape[0]):
            raise ParameterError(f"points must be vertex indices in [0, {vertices.shape[0]})")
    view_list = resolve_views(views)
    cmap, dpi = check_cmap(cmap), check_dpi(dpi)
    max_faces = check_optional_int("max_faces", max_faces, 4)
    smooth = check_shading(shading)
    lo, hi = robust_range(values, faces, vmin=vmin, vmax=vmax)
    span = value_span(values, faces)
    if figsize is None:
        figsize = (4.0 * len(view_list), 5.2 if title else 4.8)
    frame, radius = canonical_frame(vertices, up, faces)
    drawn = drawing_faces(vertices, faces, max_faces)
    geometry = Geometry(frame, drawn)
    if smooth:
        rgb = vertex_colors(values, cmap, lo, hi)[drawn]
    else:
        rgb = face_colors(values, drawn, cmap, lo, hi)
    fig = new_figure(figsize, dpi)
    bottom = BAR_SPACE / figsize[1]
    top = 1.0 - (TITLE_SPACE / figsize[1] if title else 0.0)
    if points is not None:
        points = nearest_drawn(vertices, drawn, points)
        size = float(np.clip(2400.0 / max(points.size, 1), 30.0, 110.0))
    for rect, (elev, azim) in zip(panel_rects(len(view_list), bottom, top), view_list, strict=True):
        ax = mesh_axes(fig, rect, frame, radius, elev, azim)
        draw_mesh(ax, frame, drawn, geometry, rgb, elev, azim, smooth)
        if points is None:
            continue
        visible = visible_points(frame, drawn, frame[points], direction(elev, azim))
        shown = frame[points][visible] @ screen_axes(elev, azim)[:2].T
        if shown.size:
            style = {"edgecolors": "black", "linewidths": 1.2, "zorder": 2}
            ax.scatter(shown[:, 0], shown[:, 1], s=size, c=marker_color, **style)
        text = f"{int(visible.sum())} of {points.size} points visible"
        x, y = rect[0] + rect[2] / 2, bottom - 0.06 / figsize[1]
        fig.text(x, y, text, ha="center", va="top", fontsize=8, color="0.35")
    return finish_with_colorbar(fig, cmap, lo, hi, label, title, path, span)


#: The accepted values of ``shading``.
SHADINGS = ("smooth", "flat")


def check_shading(shading) -> bool:
    """Whether ``shading`` (one of :data:`SHADINGS`) is smooth, or :class:`ParameterError`."""
    if shading not in SHADINGS:
        raise ParameterError(f"shading must be one of {', '.join(SHADINGS)}, got {shading!r}")
    return shading == "smooth"


def default_scales(num_scales: int, count: int = 5) -> list[int]:
    """About ``count`` evenly spaced 0-based scale indices, first and last included."""
    return sorted({round(float(x)) for x in np.linspace(0, num_scales - 1, min(count, num_scales))})


def render_multiscale(
    positions,
    faces,
    path,
    scales: Sequence[int] | None = None,
    *,
    view: tuple[float, float] = (20.0, -55.0),
    views: int | str | Sequence | None = None,
    up: str | None = None,
    first_scale: int = 1,
    title: str | None = None,
    figsize: tuple[float, float] | None = None,
    dpi: float = 100,
    max_faces: int | None = DRAW_FACES,
    shading: str = "smooth",
) -> Path:
    """Draw the mesh at several scales of a multiscale representation, grey shaded: one
    column per scale, one row per view.

    Args:
        positions: ``(K, V, 3)`` vertex positions per scale (``positions[0]`` the input mesh),
            sharing the ``(F, 3)`` ``faces``; ``path``: the PNG file, returned.
        scales: 0-based indices into ``positions`` to show (default: up to five, spread out).
        view: ``(elevation, azimuth)``, the one row when ``views`` is ``None``; ``views``,
            ``up``, ``title``, ``dpi``, ``max_faces``, ``shading``: as for
            :func:`render_scalar` (one decimation of ``positions[0]`` for every scale).
        first_scale: number of ``positions[0]`` in the panel titles (the paper's ``k=1``).
        figsize: default ``(3.2 * scales, 3.6 * rows)`` inches (``0.4`` more with a title).
    """
    positions = as_numpy(positions, np.float64)
    if positions.ndim != 3 or positions.shape[2] != 3 or positions.shape[0] == 0:
        raise ParameterError(f"positions must have shape (K, V, 3), got {positions.shape}")
    _, faces = check_mesh(positions[0], faces)
    num_scales = positions.shape[0]
    chosen = default_scales(num_scales) if scales is None else [int(s) for s in scales]
    if not chosen or min(chosen) < -num_scales or max(chosen) >= num_scales:
        raise ParameterError(f"scales must be indices into {num_scales} scales, got {chosen}")
    chosen = [s % num_scales for s in chosen]
    view_list = resolve_views([view] if views is None else views)
    dpi, max_faces = check_dpi(dpi), check_optional_int("max_faces", max_faces, 4)
    smooth = check_shading(shading)
    if figsize is None:
        figsize = (3.2 * len(chosen), 3.6 * len(view_list) + (0.4 if title else 0.0))

    # One frame for all panels, from the input mesh, so that shrinking is visible.
    rotation, centre, radius = frame_axes(positions[0], up, faces)
    first_frame = (positions[0] - centre) @ rotation.T
    faces = drawing_faces(positions[0], faces, max_faces)
    grey = np.full((faces.shape[0], 3), 0.82)
    fig = new_figure(figsize, dpi)
    top = 1.0 - (TITLE_SPACE / figsize[1] if title else 0.0)
    label_height = 0.35 / figsize[1]
    frames = {index: (positions[index] - centre) @ rotation.T for index in chosen}
    geometries = {index: Geometry(frame, faces) for index, frame in frames.items()}
    rows = grid_rects(len(view_list), len(chosen), 0.0, top - label_height)
    for row, (elev, azim) in zip(rows, view_list, strict=True):
        for rect, index in zip(row, chosen, strict=True):
            ax = mesh_axes(fig, rect, first_frame, radius, elev, azim)
            draw_mesh(ax, frames[index], faces, geometries[index], grey, elev, azim, smooth)
    for rect, index in zip(rows[0], chosen, strict=True):
        label = f"k={index + first_scale}"
        centre_x = rect[0] + rect[2] / 2
        fig.text(centre_x, top - label_height / 2, label, ha="center", va="center", fontsize=12)
    add_title(fig, title)
    return save_figure(fig, path)


def render_interest_points(vertices, faces, saliency, points, path, **options) -> Path:
    """:func:`render_scalar` of ``saliency`` with the ``(N,)`` vertex indices ``points`` as
    markers; ``options`` as there."""
    vertices, faces = check_mesh(vertices, faces)
    saliency = check_values(saliency, vertices.shape[0], "saliency")
    return render_scalar(vertices, faces, saliency, path, points=points, **options)


def plot_error_curves(
    radii: Sequence[float],
    per_method: Mapping[str, Mapping[str, Sequence[float]]],
    path: str | Path,
    title: str | None = None,
    dpi: float = 110,
) -> Path:
    """Draw FNE, FPE and WME against the ``(R,)`` ``radii`` (fractions of the mesh diameter)
    as three panels of a ``12 x 3.8`` inch figure, one line per method of ``per_method``
    (``{method: {"fne": (R,), "fpe": (R,), "wme": (R,)}}``, e.g. the ``mean`` of
    :func:`~stochlap_torch.evaluation.mean_error_curves`), under ``title`` (``None``: untitled);
    returns the PNG ``path``."""
    fig = new_figure((12.0, 3.8), check_dpi(dpi))
    axes = fig.subplots(1, 3)
    for ax, key in zip(axes, ("fne", "fpe", "wme"), strict=True):
        for i, (method, values) in enumerate(per_method.items()):
            marker = "osD^v<>p"[i % 8]
            ax.plot(list(radii), list(values[key]), marker=marker, ms=4, label=method)
        ax.set_xlabel("tolerance r (fraction of mesh diameter)")
        ax.set_ylabel(key.upper())
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return save_figure(fig, path, supersample=1)
